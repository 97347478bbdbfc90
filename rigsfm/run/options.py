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


@dataclass(kw_only=True)
class AdjustOptions:
    """The metric bundle adjustment after mapping (rigsfm.run.adjust)."""

    loss: Loss = Loss.CAUCHY
    loss_scale_px: float = 1.0
    max_reprojection_error_px: float = 4.0
    max_iterations: int = 200


class WorldFrame(enum.StrEnum):
    """The frame of the result (rigsfm.run.world)."""

    FLOOR = "floor"  # z = 0 on the floor, z up, origin under the rigs' centroid, x towards the first rig
    MAPPING = "mapping"  # the mapper's frame (after the metric adjustment)


@dataclass(kw_only=True)
class WorldOptions:
    frame: WorldFrame = WorldFrame.FLOOR
    plane_heights: tuple[float, ...] = ()  # metres above the floor: extra ground maps (e.g. 1.7 for heads)


@dataclass(kw_only=True)
class SelfCheckOptions:
    """The epipolar self-check on synchronised narrow images (rigsfm.run.self_check)."""

    enabled: bool = True
    max_frames: int = 1  # frame names checked (the first ones shared by two or more rigs)
    # Image j is warped into image i's view through the plane at this height (floor frame, metres) before
    # features are compared: 0 for what lies on the floor; a crowd seen from above may match better at 1.7.
    warp_height_m: float = 0.0


@dataclass(kw_only=True)
class RunOptions:
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    mapping: MappingOptions = field(default_factory=MappingOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    world: WorldOptions = field(default_factory=WorldOptions)
    self_check: SelfCheckOptions = field(default_factory=SelfCheckOptions)
    manual_matches: Path | None = None  # CSV of correspondences between wide images (rigsfm.run.manual_matches)
    overwrite: bool = False
    num_threads: int = -1  # every stage; -1: all cores
