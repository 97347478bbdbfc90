"""Stages 3-4, features and matching: features (SIFT or ASIFT, a feature cache, earlier work reused), the image
pairs worth matching, verified matches, and hand-picked matches merged."""
