"""Typed options of ``rigsfm track`` (kw-only dataclasses, StrEnum choices); imports nothing heavy."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from rigsfm.core.executors import Executor  # re-exported: rigsfm.track.options.Executor
from rigsfm.run.options import INT_MAX, _check_range


@dataclass(frozen=True, kw_only=True)
class Thresholds:
    """When a frame is flagged and a change is a step (rigsfm.track.verdict)."""

    rotation_deg: float = 0.05
    translation_mm: float = 5.0
    significance_chi2: float = 16.27  # chi-square with 3 degrees of freedom at 99.9 %
    min_persist_frames: int = 3
    persist_fraction: float = 0.75
    step_to_spread: float = 2.0  # a step must be this many times the frames' median spread about their level

    def __post_init__(self) -> None:  # an infinite threshold fails the verdict after every frame is registered
        _check_range("--rotation-threshold-deg", self.rotation_deg, 0.0, 180.0)
        _check_range("--translation-threshold-mm", self.translation_mm, 0.0, 1e6)
        _check_range("significance_chi2", self.significance_chi2, 0.0, 1e6, low_open=True)
        _check_range("min_persist_frames", self.min_persist_frames, 1, INT_MAX, integer=True)
        _check_range("persist_fraction", self.persist_fraction, 0.0, 1.0, low_open=True)
        _check_range("step_to_spread", self.step_to_spread, 0.0, 1e6, low_open=True)


@dataclass(frozen=True, kw_only=True)
class RegistrationOptions:
    """How one frame of one rig is registered against the reference map (rigsfm.track.pose)."""

    max_ratio: float = 0.8  # Lowe's ratio test, as in `rigsfm run`
    max_num_features: int = 8192  # SIFT, as in `rigsfm run`
    max_error_px: float = 4.0  # RANSAC inlier threshold
    min_matches: int = 12  # a sensor with fewer 2D-3D matches is not used
    min_inliers: int = 30  # fewer: the frame is reported as not registered
    use_narrow: bool | None = None  # None: narrow images only for rigs whose narrow image has map points
    seed: int = 0

    def __post_init__(self) -> None:
        _check_range("max_ratio", self.max_ratio, 0.0, 1.0, low_open=True)
        _check_range("max_num_features", self.max_num_features, 1, 1_000_000, integer=True)
        _check_range("max_error_px", self.max_error_px, 0.0, 1000.0, low_open=True)
        _check_range("min_matches", self.min_matches, 1, INT_MAX, integer=True)
        _check_range("min_inliers", self.min_inliers, 1, INT_MAX, integer=True)
        _check_range("seed", self.seed, -1, INT_MAX, integer=True)


@dataclass(frozen=True, kw_only=True)
class TrackOptions:
    executor: Executor = Executor.LOCAL
    address: str | None = None  # a Ray cluster's address (executor ray); None starts a local Ray instance
    workers: int = field(default_factory=lambda: max(1, os.cpu_count() or 1))
    thresholds: Thresholds = field(default_factory=Thresholds)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    overwrite: bool = False  # discard earlier results and register every frame again
    checkpoint_every: int = 50  # frames between two saves of poses.json
