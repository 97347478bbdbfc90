"""Stage 3: features, image pairs and verified matches (SIFT or ASIFT, a feature cache, hand-picked matches)."""
