"""What the adjustment returns: its result, the scale's source, the gauge, each rig's calibration decision, and
the joint covariance type (``covariance.joint_covariance`` computes it)."""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.priors import CalibrationPriors
from rigsfm.run.adjustment.scale import ScaleEstimate
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.options import AdjustOptions, Calibration


class ScaleSource(enum.StrEnum):
    MEASUREMENTS = "measurements"  # scale.yaml
    NARROW_BASELINES = "narrow_baselines"  # metric E^sl with observations in narrow images
    NONE = "none"  # arbitrary units


class Gauge(enum.StrEnum):
    RIGID = "rigid"  # one frame held; the scale is observed
    TWO_CAMS_FROM_WORLD = "two_cams_from_world"  # COLMAP's: one frame and one coordinate of a second


@dataclass
class AdjustResult:
    reconstruction: pycolmap.Reconstruction
    scale_source: ScaleSource
    scale: ScaleEstimate | None  # measurements against the final model
    metres_per_mapping_unit: float | None
    mean_reprojection_error_px: float
    scale_relative_sigma: float | None = None  # of a scale set by the narrow baselines; REFINE: of the network's size
    calibration: Calibration = Calibration.FIXED
    gauge: Gauge = Gauge.TWO_CAMS_FROM_WORLD  # of the adjustment (and of its covariance)
    rigs: tuple[RigCalibration, ...] = ()  # the calibration file the adjustment started from
    priors: CalibrationPriors | None = None
    scale_spec: ScaleSpec | None = None
    options: AdjustOptions = field(default_factory=AdjustOptions)
    pixel_sigma: float | None = None  # REFINE: estimated reprojection noise (px per image coordinate)
    rounds: int = 0
    seconds: float = 0.0
    covariance: JointCovariance | None = None  # rigsfm.run.adjustment.covariance.joint_covariance, once computed
    held_rigs: frozenset[str] = frozenset()  # REFINE: rigs whose calibration was held at rigs.yaml's (hold_or_refine)
    decisions: list[CalibrationDecision] = field(default_factory=list)  # REFINE: per rig, held or refined and why
    influential: InfluentialTracks | None = None  # REFINE: the tracks that pulled the calibration (None: not scored)
    warnings: list[str] = field(default_factory=list)  # for the run's summary
    # point3D_id -> its observations' own noise (px per coordinate; heads): weighed so in the adjustment and its
    # covariance (rigsfm.run.adjustment.problem.JointProblem), the pooled pixel_sigma is the other observations'
    point_sigmas: dict[int, float] = field(default_factory=dict)
    # px per image coordinate: the error one view's point_sigmas observations share (heads; the covariance's
    # rigsfm.run.adjustment.heads_error), beside their own noise: an offset, and a tilt reaching this at the edges of
    # the view's heads. Zero in a run (benchmarks/head_band.py measures them; benchmarks/README.md says why).
    point_shared_sigma: float = 0.0
    point_shared_slope_sigma: float = 0.0


@dataclass(frozen=True)
class InfluentialTracks:
    """The tracks removed before the hold-or-refine test because each alone pulled the refined calibration
    (``rigsfm.run.adjustment.influence``; ``adjust.MAX_TRACK_INFLUENCE``)."""

    removed: int = 0  # tracks, every round
    rounds: int = 0  # scorings of the refined adjustment; the last found none above the threshold unless capped
    per_round: tuple[int, ...] = ()  # tracks removed after each scoring
    largest_kept: float = 0.0  # the largest score of a track kept, in the last scoring
    threshold: float = 0.0
    seconds: float = 0.0  # scoring and adjusting again


@dataclass(frozen=True)
class CalibrationDecision:
    """One rig's calibration after :func:`hold_or_refine`: ``held`` at rigs.yaml's values or refined, and why."""

    rig: str
    held: bool
    reason: str  # one clause
    largest_gain: float = 0.0  # the largest share of one direction's prior variance the images removed (this rig)
    chi2: float = 0.0  # the refinement's change against the spread the images explain (consistency test)
    dof: int = 0
    limit: float = 0.0  # the chi-square's HOLD_QUANTILE quantile
    network_chi2: float = 0.0  # the same test over the whole network's calibration (every rig's decision)
    network_dof: int = 0


@dataclass(frozen=True)
class JointCovariance:
    """Joint covariance of rig poses and calibration, points marginalised out (``rigsfm.run.adjustment.covariance``).
    Held parameters (the gauge, sigma-0 intrinsics) have zero rows."""

    keys: tuple[tuple[str, int], ...]
    offsets: dict
    covariance: np.ndarray
    pixel_sigma: float  # the images' weighting noise (estimated noise x AdjustOptions.pixel_sigma_inflation)
    kind: str  # "posterior" (REFINE) or "consider" (FIXED)
    prior_only: frozenset = frozenset()
    seconds: float = 0.0
    # REFINE: how much wider the refined calibration's change from rigs.yaml spreads than prior minus posterior (the
    # solve weighs residuals the noise model counts as correlated as independent; covariance._change_excess), in the
    # covariance's layout; None where the solve is weighted as the noise model
    change_excess: np.ndarray | None = None

    def slice(self, key) -> slice:
        start, size = self.offsets[key]
        return slice(start, start + size)

    def index(self, keys: Sequence) -> np.ndarray:
        return np.concatenate([np.arange(self.offsets[k][0], sum(self.offsets[k])) for k in keys])

    def sub(self, keys: Sequence) -> np.ndarray:
        index = self.index(keys)
        return self.covariance[np.ix_(index, index)]

    def sigma(self, key) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance[self.slice(key), self.slice(key)]), 0.0, None))
