"""Stages 6 and 8, adjust and uncertainty: the metric bundle adjustment with the rigs' calibration (the problem,
priors and costs, hold-or-refine), and what its result is worth (the joint covariance, each narrow camera's
uncertainty, each narrow pair's epipolar band)."""
