"""Typed options of ``rigsfm run`` (kw-only dataclasses, StrEnum choices).

This module imports nothing heavy, so the command line can build its help from it at once.
"""

from __future__ import annotations

import enum
import math
import numbers
import os
from dataclasses import dataclass, field
from pathlib import Path

from rigsfm.core.errors import InputError
from rigsfm.core.executors import Executor  # also the command line's


def _check_range(name: str, value, low: float, high: float, *, low_open: bool = False, integer: bool = False) -> None:
    """``value`` a (finite) number in [low, high] ((low, high] with ``low_open``); an ``InputError`` naming the
    option and its range otherwise (NaN included: it passes every comparison)."""
    number_ok = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, bool)
    if not number_ok or not math.isfinite(value) or value > high or value < low or (low_open and value == low):
        kind = "an integer" if integer else "a number"
        show = (lambda v: str(int(v))) if integer else (lambda v: f"{v:g}")
        bounds = f"{'>' if low_open else '>='} {show(low)} and <= {show(high)}"
        raise InputError(f"{name} must be {kind} {bounds}, got {value!r}")


INT_MAX = 2**31 - 1  # COLMAP's C++ options are ints: a larger number fails there, after the heavy stages


def _choice(kind: type[enum.StrEnum], value, name: str):
    try:
        return kind(value)
    except ValueError:
        raise InputError(f"{name} must be one of {', '.join(kind)}, got {value!r}") from None


class Features(enum.StrEnum):
    SIFT = "sift"  # COLMAP's SIFT
    ASIFT = "asift"  # affine-simulated SIFT (rigsfm.run.matching.asift), for large perspective changes between rigs


class NarrowMode(enum.StrEnum):
    """Narrow observations (rigsfm.run.narrow): synchronised narrow images matched after a first adjustment."""

    AUTO = "auto"  # used where the narrow images carry usable texture (a guided match count per pair)
    ON = "on"  # used wherever they give matches
    OFF = "off"  # never (wide-only adjustment)


class Pairs(enum.StrEnum):
    """Which pairs of featured images are matched fully (rigsfm.run.matching.pairs.select_pairs)."""

    AUTO = "auto"  # a cheap first pass picks each image's best partners: about linear in the images
    EXHAUSTIVE = "exhaustive"  # every pair: quadratic in the images


class Device(enum.StrEnum):
    """Where SIFT extraction and matching run (rigsfm.run.matching.gpu.use_gpu)."""

    AUTO = "auto"  # a CUDA GPU when pycolmap is built with CUDA (rigsfm[gpu]) and one is found, else the CPU
    CPU = "cpu"
    CUDA = "cuda"  # the GPU or a clear error


class Mapper(enum.StrEnum):
    """COLMAP's mapper for the wide images. AUTO picks by network size (:attr:`MappingOptions.global_from_frames`)."""

    AUTO = "auto"
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
    # SIFT's first octave: -1 doubles the image first (COLMAP's default), 0 does not (far less CPU and memory).
    # None: 0 for networks of rigsfm.run.matching.extract.COARSE_SIFT_MIN_FRAMES wide frames or more whose
    # images are COARSE_SIFT_MIN_SIDE_PX or larger, -1 otherwise (rigsfm.run.matching.extract.resolved_first_octave).
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
    # With narrow features: per-rig frame offsets (rigsfm.run.checks.sync) of an unsynchronised recording; narrow images
    # of two rigs are matched only when taken at the same time. None: not applied (frame names as they are).
    frame_offsets: dict[str, int] | None = None

    def __post_init__(self) -> None:
        _check_range("--max-ratio (Lowe's ratio test)", self.max_ratio, 0.0, 1.0, low_open=True)
        _check_range("max_num_features", self.max_num_features, 1, 1_000_000, integer=True)
        _check_range("max_error_px", self.max_error_px, 0.0, 1000.0, low_open=True)
        _check_range("max_homography_inlier_ratio", self.max_homography_inlier_ratio, 0.0, 1.0, low_open=True)
        self.features = _choice(Features, self.features, "--features")
        self.pairs = _choice(Pairs, self.pairs, "--pairs")
        self.device = _choice(Device, self.device, "--device")
        _check_range("--neighbours", self.neighbours, 1, 10_000, integer=True)

    @property
    def resolved_rig_verification(self) -> bool:
        return (not self.narrow_features) if self.rig_verification is None else self.rig_verification


# --mapper auto: the global mapper from this many wide frames (faster there at the same accuracy), the incremental
# one below, where the global mapper alone can fail on small featureless circles; the incremental one hands the
# frames it cannot reach to the global mapper (see benchmarks/README.md).
GLOBAL_FROM_FRAMES = 16


@dataclass(kw_only=True)
class MappingOptions:
    mapper: Mapper = Mapper.AUTO
    global_from_frames: int = GLOBAL_FROM_FRAMES  # AUTO's threshold
    seed: int = 0
    # Lower COLMAP's match-count thresholds (rigsfm.run.mapping.mapper.relax_for_few_matches). None: on when manual
    # matches are given, off otherwise. Not on by default: relaxed, a pair of rigs with 21 wrong-but-consistent
    # SIFT matches registers 70 degrees off instead of failing with a clear message.
    few_matches: bool | None = None
    # The incremental mapper stops after this long (seconds; None: never) and the global mapper is used instead,
    # with a warning; a safety net: with its initial pair chosen up front it maps 12 rigs in under a minute.
    incremental_time_limit_s: int | None = 900

    def __post_init__(self) -> None:
        self.mapper = _choice(Mapper, self.mapper, "--mapper")
        _check_range("global_from_frames", self.global_from_frames, 2, 10**9, integer=True)
        _check_range("--seed (-1: random)", self.seed, -1, INT_MAX, integer=True)
        if self.incremental_time_limit_s is not None:
            _check_range("--incremental-time-limit (seconds)", self.incremental_time_limit_s, 0, INT_MAX,
                         integer=True)


class Calibration(enum.StrEnum):
    """What the metric bundle adjustment does with rigs.yaml's intrinsics and E^sl."""

    REFINE = "refine"  # refined with the images, each weighted by its calibration sigma (rigsfm.run.adjustment.priors)
    FIXED = "fixed"  # held exactly at rigs.yaml (--fixed-calibration)


@dataclass(kw_only=True)
class AdjustOptions:
    """The metric bundle adjustment after mapping (rigsfm.run.adjustment.adjust)."""

    loss: Loss = Loss.CAUCHY
    loss_scale_px: float = 1.0
    max_reprojection_error_px: float = 4.0
    max_iterations: int = 200
    calibration: Calibration = Calibration.REFINE
    # REFINE: the images' weight against the calibration priors and measurements. Reprojection residuals count
    # as if their noise were this many times the one estimated from them: SIFT positions err systematically
    # between views far apart, and at 1 the images pull the intrinsics further than the posterior allows (see
    # benchmarks/README.md).
    pixel_sigma_inflation: float = 3.0
    max_rounds: int = 4  # REFINE: adjust, drop outliers, re-estimate the pixel noise; until nothing changes

    def __post_init__(self) -> None:
        self.loss = _choice(Loss, self.loss, "loss")
        _check_range("loss_scale_px", self.loss_scale_px, 0.0, 1000.0, low_open=True)
        _check_range("max_reprojection_error_px", self.max_reprojection_error_px, 0.0, 1000.0, low_open=True)
        _check_range("max_iterations", self.max_iterations, 1, 1_000_000, integer=True)


class WorldFrame(enum.StrEnum):
    """The frame of the result (rigsfm.run.world.frame)."""

    FLOOR = "floor"  # z = 0 on the floor, z up, origin under the rigs' centroid, x towards the first rig
    MAPPING = "mapping"  # the mapper's frame (after the metric adjustment)


@dataclass(kw_only=True)
class WorldOptions:
    frame: WorldFrame = WorldFrame.FLOOR
    plane_heights: tuple[float, ...] = ()  # metres above the floor: extra ground maps (e.g. 1.7 for heads)


@dataclass(kw_only=True)
class SelfCheckOptions:
    """The epipolar self-check on synchronised narrow images (rigsfm.run.checks.self_check)."""

    enabled: bool = True
    max_frames: int = 1  # frame names checked (the first ones shared by two or more rigs)
    # Image j is warped into image i's view through the plane at this height (floor frame, metres) before
    # features are compared: 0 for what lies on the floor; a crowd seen from above may match better at 1.7.
    warp_height_m: float = 0.0
    # OpenCV SIFT runs on the narrow images (and warps) reduced by the integer factor that brings their longer
    # side nearest this (1624x1234 -> 2, 812x617 -> 1): faster, with distances as close to the truth (see
    # benchmarks/README.md).
    sift_size: int = 800
    # Per-rig frame offsets of the narrow images (rigsfm.run.checks.sync): None checks synchronisation when the check
    # fails; "auto" estimates the offsets and pairs the frames by time; a path: a yaml file 'rig03: 1' applied.
    frame_offsets: str | Path | None = None
    max_offset_frames: int = 2  # offsets searched: -this .. this (and within the recording)

    def __post_init__(self) -> None:
        _check_range("--max-offset-frames", self.max_offset_frames, 0, 1000, integer=True)
        if self.frame_offsets is not None and str(self.frame_offsets) != "auto":
            self.frame_offsets = Path(self.frame_offsets)
        _check_range("self-check max_frames", self.max_frames, 1, 1_000_000, integer=True)
        _check_range("self-check warp_height_m", self.warp_height_m, -1000.0, 1000.0)
        _check_range("self-check sift_size", self.sift_size, 16, 100_000, integer=True)


@dataclass(kw_only=True)
class RunOptions:
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    mapping: MappingOptions = field(default_factory=MappingOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    world: WorldOptions = field(default_factory=WorldOptions)
    self_check: SelfCheckOptions = field(default_factory=SelfCheckOptions)
    narrow: NarrowMode = NarrowMode.AUTO  # narrow observations after a first adjustment (rigsfm.run.narrow)
    manual_matches: Path | None = None  # CSV of correspondences between wide images (rigsfm.run.matching.manual_matches)
    overwrite: bool = False
    num_threads: int = -1  # every stage; -1: all cores
    # Feature extraction: local (pycolmap's threads on this machine) or ray (one task per image on a Ray
    # cluster at ``address``; None starts a local Ray instance with ``workers`` CPUs). Same features either way.
    executor: Executor = Executor.LOCAL
    address: str | None = None
    workers: int = field(default_factory=lambda: max(1, os.cpu_count() or 1))

    def __post_init__(self) -> None:
        if self.num_threads != -1:
            _check_range("num_threads (-1: all cores)", self.num_threads, 1, 4096, integer=True)
        self.executor = _choice(Executor, self.executor, "--executor")
        self.narrow = _choice(NarrowMode, self.narrow, "--narrow")
        _check_range("workers", self.workers, 1, 100_000, integer=True)
        if self.address is not None and self.executor != Executor.RAY:
            raise InputError("--address is the address of a Ray cluster: use it with --executor ray")
