"""Typed options of ``rigsfm run`` (kw-only dataclasses, StrEnum choices).

This module imports nothing heavy, so the command line can build its help from it at once.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path


class Features(enum.StrEnum):
    SIFT = "sift"  # COLMAP's SIFT
    ASIFT = "asift"  # affine-simulated SIFT (rigsfm.run.asift), for large perspective changes between rigs


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
    # Verify pairs of frames with the rigs' generalized relative pose. None: on unless narrow features
    # are extracted (with textured narrow views it took over 15 minutes for 24 images).
    rig_verification: bool | None = None
    narrow_features: bool = False
    max_error_px: float = 4.0  # RANSAC threshold of the two-view geometry
    max_homography_inlier_ratio: float = 0.95

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


class Calibration(enum.StrEnum):
    """What the metric bundle adjustment does with rigs.yaml's intrinsics and E^sl."""

    REFINE = "refine"  # refined with the images, each weighted by its calibration sigma (rigsfm.run.priors)
    FIXED = "fixed"  # held exactly at rigs.yaml (--fixed-calibration; rigsfm before issue 13)


@dataclass(kw_only=True)
class AdjustOptions:
    """The metric bundle adjustment after mapping (rigsfm.run.adjust)."""

    loss: Loss = Loss.CAUCHY
    loss_scale_px: float = 1.0
    max_reprojection_error_px: float = 4.0
    max_iterations: int = 200
    calibration: Calibration = Calibration.REFINE
    # REFINE: the images' weight against the calibration priors and measurements. Reprojection residuals count
    # as if their noise were this many times the one estimated from them: SIFT positions err systematically
    # between views 45-60 deg apart, and at 1 the images pulled the wide intrinsics 2-4x further from the truth
    # than the posterior allowed (rendered arena; the band then held 89 % instead of 95 %).
    pixel_sigma_inflation: float = 3.0
    max_rounds: int = 4  # REFINE: adjust, drop outliers, re-estimate the pixel noise; until nothing changes


@dataclass(kw_only=True)
class RunOptions:
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    mapping: MappingOptions = field(default_factory=MappingOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    manual_matches: Path | None = None  # CSV of correspondences between wide images (rigsfm.run.manual_matches)
    overwrite: bool = False
    num_threads: int = -1  # every stage; -1: all cores
