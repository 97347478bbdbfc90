"""Stages 10-11, check_pairs and self_check, and the diagnostics in summary.json: what a user cannot see in the
reprojection errors (rigidity, weak or contradicted links, missed pairs, the epipolar self-check)."""
