"""Typed options of ``rigsfm run`` (kw-only dataclasses, StrEnum choices).

This module imports nothing heavy, so the command line can build its help from it at once.
"""

from __future__ import annotations

import enum
import os
from dataclasses import dataclass, field
from pathlib import Path

from rigsfm.core.executors import Executor  # noqa: F401  (re-exported for the command line)


class Features(enum.StrEnum):
    SIFT = "sift"  # COLMAP's SIFT
    ASIFT = "asift"  # affine-simulated SIFT (rigsfm.run.asift), for large perspective changes between rigs


class Pairs(enum.StrEnum):
    """Which pairs of featured images are matched fully (rigsfm.run.features.select_pairs)."""

    AUTO = "auto"  # a cheap first pass picks each image's best partners: about linear in the images
    EXHAUSTIVE = "exhaustive"  # every pair: quadratic in the images


class Device(enum.StrEnum):
    """Where SIFT extraction and matching run (rigsfm.run.gpu.use_gpu)."""

    AUTO = "auto"  # a CUDA GPU when pycolmap is built with CUDA (rigsfm[gpu]) and one is found, else the CPU
    CPU = "cpu"
    CUDA = "cuda"  # the GPU or a clear error


class Mapper(enum.StrEnum):
    INCREMENTAL = "incremental"
    GLOBAL = "global"


class Loss(enum.StrEnum):
    """Robust loss of the reprojection residuals in the metric bundle adjustment (COLMAP's names)."""

    CAUCHY = "CAUCHY"
    HUBER = "HUBER"
    SOFT_L1 = "SOFT_L1"
    TRIVIAL = "TRIVIAL"


@dataclass(kw_only=True)
class MatchingOptions:
    features: Features = Features.SIFT
    max_ratio: float = 0.8  # Lowe's ratio test
    cross_check: bool = True  # mutual nearest neighbours
    max_num_features: int = 8192
    # SIFT's first octave: -1 doubles the image first (COLMAP's default), 0 does not (3.3x less CPU, 2.9x less
    # memory). None: 0 for networks of rigsfm.run.features.COARSE_SIFT_MIN_FRAMES wide frames or more whose
    # images are COARSE_SIFT_MIN_SIDE_PX or larger, -1 otherwise (rigsfm.run.features.resolved_first_octave).
    first_octave: int | None = None
    # Verify pairs of frames with the rigs' generalized relative pose. None: on unless narrow features
    # are extracted (with textured narrow views it took over 15 minutes for 24 images).
    rig_verification: bool | None = None
    narrow_features: bool = False
    max_error_px: float = 4.0  # RANSAC threshold of the two-view geometry
    max_homography_inlier_ratio: float = 0.95
    pairs: Pairs = Pairs.AUTO
    neighbours: int = 8  # with pairs auto: the best partners kept per image (of other rigs)
    device: Device = Device.AUTO

    @property
    def resolved_rig_verification(self) -> bool:
        return (not self.narrow_features) if self.rig_verification is None else self.rig_verification


@dataclass(kw_only=True)
class MappingOptions:
    mapper: Mapper = Mapper.INCREMENTAL
    seed: int = 0
    # Lower COLMAP's match-count thresholds (rigsfm.run.mapping.relax_for_few_matches). None: on when manual
    # matches are given, off otherwise. Not on by default: relaxed, a pair of rigs with 21 wrong-but-consistent
    # SIFT matches registers 70 degrees off instead of failing with a clear message.
    few_matches: bool | None = None


@dataclass(kw_only=True)
class AdjustOptions:
    """The metric bundle adjustment after mapping (rigsfm.run.adjust)."""

    loss: Loss = Loss.CAUCHY
    loss_scale_px: float = 1.0
    max_reprojection_error_px: float = 4.0
    max_iterations: int = 200


@dataclass(kw_only=True)
class RunOptions:
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    mapping: MappingOptions = field(default_factory=MappingOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    manual_matches: Path | None = None  # CSV of correspondences between wide images (rigsfm.run.manual_matches)
    overwrite: bool = False
    num_threads: int = -1  # every stage; -1: all cores
    # Feature extraction: local (pycolmap's threads on this machine) or ray (one task per image on a Ray
    # cluster at ``address``; None starts a local Ray instance with ``workers`` CPUs). Same features either way.
    executor: Executor = Executor.LOCAL
    address: str | None = None
    workers: int = field(default_factory=lambda: max(1, os.cpu_count() or 1))
