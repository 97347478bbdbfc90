"""Typed options of ``rigsfm track`` (kw-only dataclasses, StrEnum choices); imports nothing heavy."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from rigsfm.core.executors import Executor  # noqa: F401  (re-exported: rigsfm.track.options.Executor)


@dataclass(frozen=True, kw_only=True)
class Thresholds:
    """When a frame is flagged and a change is a step (rigsfm.track.verdict)."""

    rotation_deg: float = 0.05
    translation_mm: float = 5.0
    significance_chi2: float = 16.27  # chi-square with 3 degrees of freedom at 99.9 %
    min_persist_frames: int = 3
    persist_fraction: float = 0.75
    step_to_spread: float = 2.0  # a step must be this many times the frames' median spread about their level


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


@dataclass(frozen=True, kw_only=True)
class TrackOptions:
    executor: Executor = Executor.LOCAL
    address: str | None = None  # a Ray cluster's address (executor ray); None starts a local Ray instance
    workers: int = field(default_factory=lambda: max(1, os.cpu_count() or 1))
    thresholds: Thresholds = field(default_factory=Thresholds)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    overwrite: bool = False  # discard earlier results and register every frame again
    checkpoint_every: int = 50  # frames between two saves of poses.json
