"""Stage 1-2: every input validated before any heavy work (images, scale.yaml), and the COLMAP database."""
