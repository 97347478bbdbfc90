"""Stages 5 and 7: the metric bundle adjustment with the rigs' calibration, and what its result is worth
(the joint covariance, each narrow camera's uncertainty, each narrow pair's epipolar band)."""
