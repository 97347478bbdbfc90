"""Stage 7, world: the floor frame (z = 0 on the floor, z up, metres) from the floor fit and floor matching, the
floor the bands use, and the ground maps."""
