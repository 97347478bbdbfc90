"""Stage 6: the world frame (the floor fit, z = 0 on the floor, z up, metres) and the ground maps."""
