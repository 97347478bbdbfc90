"""Stages 7-9 checks: diagnostics of the reconstruction, missed pairs, and the epipolar self-check."""
