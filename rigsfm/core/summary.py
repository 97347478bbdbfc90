"""summary.json: what a run did and what its result is worth, as one typed record (:class:`Summary`).

Written by ``rigsfm run`` (``Summary.to_json``), read by the report, ``rigsfm export`` and the command line
(``Summary.read``; summaries of older runs read with defaults for what they lack).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from rigsfm.core.errors import WorkspaceError

# matches a self-check pair needs for a verdict (fewer: its 95th percentile is set by two or three matches)
SELF_CHECK_MIN_MATCHES = 50


@dataclass(kw_only=True)
class Registration:
    registered: int = 0
    total: int = 0


@dataclass(kw_only=True)
class CameraError:
    """Reprojection error of one camera (``<rig>/<sensor>``) over its observations."""

    observations: int = 0
    mean_px: float | None = None
    rms_px: float | None = None


@dataclass(kw_only=True)
class ScaleSummary:
    source: str = "none"  # measurements, narrow_baselines or none (rigsfm.run.adjustment.result.ScaleSource)
    metres_per_mapping_unit: float | None = None
    relative_sigma_percent: float | None = None
    measurements: list[dict] = field(default_factory=list)  # rigsfm.run.adjustment.scale.ScaleEstimate.residuals()


@dataclass(kw_only=True)
class MappingSummary:
    asked: str = ""  # the --mapper asked for
    used: str = ""  # the mapper whose model was kept
    fallback: str | None = None  # why it differs from the one asked for
    few_matches: bool = False  # COLMAP's match thresholds lowered (manual matches)


@dataclass(kw_only=True)
class InputsSummary:
    images: str = ""
    num_rigs: int = 0
    scale_file: str | None = None


@dataclass(kw_only=True)
class NarrowUncertaintySummary:
    """1 sigma of one narrow camera relative to the network (rigsfm.run.adjustment.narrow.narrow_uncertainty)."""

    centre_sigma_mm: float | None = None
    rotation_sigma_deg: float | None = None
    centre_covariance_mm2: list[list[float]] | None = None  # 3x3, in the camera's axes (x right, y down, z forward)
    rotation_covariance_deg2: list[list[float]] | None = None  # 3x3, in the camera's axes
    # A result that is not metric has no millimetre: its centre values are in the mapping unit here, and the _mm keys
    # null (as scale.metres_per_mapping_unit is)
    centre_sigma_units: float | None = None
    centre_covariance_units2: list[list[float]] | None = None

    def centre_sigma_in_model_units(self) -> float | None:
        """The centre's 1 sigma in the model's unit (metres where metric); summaries of older runs without a scale
        wrote the mapping unit's thousandths under ``centre_sigma_mm``."""
        if self.centre_sigma_mm is not None:
            return self.centre_sigma_mm / 1000.0
        return self.centre_sigma_units


@dataclass(kw_only=True)
class PairBandSummary:
    """One narrow pair's 95 % epipolar band (rigsfm.run.adjustment.bands.PairBand)."""

    i: str = ""
    j: str = ""
    band_px: float | None = None
    points: str | None = None  # floor or depths
    predicted_below_85: float | None = None  # the model's probability that < 85 % of this pair's points are inside


BANDS_WITH_NARROW = "with narrow observations"  # UncertaintySummary.bands_from: the adjustment with them
BANDS_WIDE_ONLY = "wide only"  # ... and the adjustment without them


@dataclass(kw_only=True)
class UncertaintySummary:
    calibration: str = "fixed"  # refine or fixed (rigsfm.run.options.Calibration)
    covariance: str | None = None  # posterior (refine) or consider (fixed); None when it could not be estimated
    pixel_sigma_px: float | None = None  # the images' weighting noise per coordinate (estimated x inflation)
    floor: str = "none"  # where the bands' analysis points lie: known_lengths, points, none (depths)
    bands: str = "linear"  # linear in the covariance, or sampled (re-adjusted over calibration draws: <= 3 rigs)
    bands_from: str = BANDS_WIDE_ONLY  # the adjustment they are of: BANDS_WITH_NARROW or BANDS_WIDE_ONLY
    narrow: dict[str, NarrowUncertaintySummary] = field(default_factory=dict)  # per narrow image
    pairs: list[PairBandSummary] = field(default_factory=list)
    refined_calibration: dict[str, dict] = field(default_factory=dict)  # per camera: change and posterior sigma


@dataclass
class MissedPairSummary:
    image_a: str = ""
    image_b: str = ""
    predicted_points: int = 0  # model points seen by one image that the other sees from a similar direction
    weakest_matched: int = 0  # the same count for the weakest pair matched for either image


@dataclass
class PairsSummary:
    """The image pairs: candidates, matched and skipped (rigsfm.run.matching.pairs), and the skipped pairs the model
    says would have shared many points (rigsfm.run.checks.missed_pairs)."""

    mode: str = "auto"
    candidates: int = 0
    matched: int = 0
    skipped: int = 0
    first_pass_s: float = 0.0
    missed: list[MissedPairSummary] = field(default_factory=list)  # the worst ones first, at most 20
    num_missed: int = 0


@dataclass
class FrameOffsetsSummary:
    """Per-rig frame offsets of the narrow images (rigsfm.run.checks.sync)."""

    asked: str | None = None  # "auto", a file, or None (estimated only when the self-check fails)
    applied: dict[str, int] = field(default_factory=dict)  # rig -> frames
    estimate: dict | None = None  # the estimate's record, when one was made


def floor_from_markers_alone(points_by_source: dict | None, num_points: int | None) -> bool:
    """Whether a floor fit rests on the known-length markers alone (rigsfm.run.world.floor_fit.marker_floor: a crowd
    hid the floor from the points), from its record's ``points_by_source`` and ``num_points``."""
    if not points_by_source:
        return False
    return points_by_source.get("markers") == num_points


@dataclass(kw_only=True)
class WorldSummary:
    """The result's frame and its floor fit (rigsfm.run.world.frame.WorldResult.summary); also narrow_poses.json's
    ``world``."""

    asked: str = ""  # floor or mapping (rigsfm.run.options.WorldFrame)
    frame: str = ""  # the frame used
    units: str | None = None  # the floor frame's description: units to plane_heights_m (None in the mapper's)
    origin: str | None = None
    x_axis: str | None = None
    z_axis: str | None = None
    plane_heights_m: list[float] | None = None
    description: str | None = None  # the mapper's frame's description (None in the floor frame)
    floor: dict | None = None  # the floor fit's record (rigsfm.run.world.floor_fit), when one was tried

    def to_json(self) -> dict:
        # the keys of the other frame are left out, not written as null (the file's form since the floor frame)
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(kw_only=True)
class SelfCheckSettings:
    wide_factor: float = 5.0  # rigsfm.run.checks.guided.WIDE_FACTOR
    keypoint_noise_px: float = 1.0
    min_matches: int = SELF_CHECK_MIN_MATCHES
    top_height_m: float = 2.2


@dataclass(kw_only=True)
class SelfCheckPairSummary:
    """One narrow pair of the self-check (rigsfm.run.checks.guided.PairCheck)."""

    frame: str = ""
    i: str = ""
    j: str = ""
    band_px: float | None = None
    matches: int = 0
    median_px: float | None = None
    p95_px: float | None = None
    within_band: float | None = None  # share of the matches within band_px + keypoint noise (settings)
    band_matches: int = 0
    measured_within_px: float | None = None
    verdict: str = "too few matches"


@dataclass(kw_only=True)
class SelfCheckSummary:
    """The epipolar self-check on synchronised narrow images (rigsfm.run.checks.self_check.SelfCheck.summary)."""

    frames: list[str] = field(default_factory=list)
    guided_by: str = ""
    skipped: str | None = None  # why nothing was checked
    frame_offsets: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    settings: SelfCheckSettings = field(default_factory=SelfCheckSettings)
    pairs: list[SelfCheckPairSummary] = field(default_factory=list)


@dataclass(kw_only=True)
class NarrowPairSummary:
    """One narrow pair's guided matches (rigsfm.run.narrow.observations.PairMatches)."""

    frame: str = ""
    i: str = ""
    j: str = ""
    found: int = 0
    matches: int = 0
    spread_px: float | None = None
    search_px: float = 0.0
    textured: bool = False
    in_adjustment: bool = False
    held_out: int = 0
    searched: float = 1.0  # share of i's keypoints searched (the candidate budget: whole epipolar lines, no floor)


@dataclass(kw_only=True)
class HeldOutCheckSummary:
    """One pair's held-out matches against its band (rigsfm.run.narrow.observations.HeldOutCheck)."""

    i: str = ""
    j: str = ""
    band_px: float | None = None
    held_out: int = 0
    median_px: float | None = None
    p95_px: float | None = None
    within_band: float | None = None  # share of the held-out matches within band_px + keypoint noise
    verdict: str = "too few matches"


@dataclass(kw_only=True)
class NarrowObservationsSummary:
    """What ``--narrow`` decided and did (rigsfm.run.narrow.observations.NarrowObservations.summary)."""

    asked: str = ""
    used: bool = False
    reason: str = ""
    seconds: float = 0.0
    points_added: int = 0
    observations_added: int = 0
    held_out_matches: int = 0
    pairs: list[NarrowPairSummary] = field(default_factory=list)
    held_out_check: list[HeldOutCheckSummary] = field(default_factory=list)
    bands: str | None = None  # which adjustment the delivered bands are from, when used
    matched_by: str = "floor warp"  # or "heads": persons matched across views (rigsfm.run.narrow.heads)
    head_persons: int | None = None  # confident persons the heads' association found, where it ran
    head_candidates: int | None = None  # head candidates in the narrow images, where searched
    head_verdicts: int = 0  # self-check pairs whose verdict comes from their head matches
    head_sigma_px: float | None = None  # the noise per coordinate the heads' observations were weighed at, where used
    # The heads' frame-offset check of a recording (rigsfm.run.narrow.timing; rigsfm.associate.sync.SyncCheck's
    # record), where the heads were matched without given offsets
    head_frame_offsets: dict | None = None


@dataclass(kw_only=True)
class ManualPairSummary:
    """One image pair of --manual-matches (rigsfm.run.matching.manual_merge.PairReport)."""

    image_a: str = ""
    image_b: str = ""
    given: int = 0
    kept: int = 0
    automatic_inliers: int = 0
    inliers_after: int = 0
    config: str = ""
    rejected: list[dict] = field(default_factory=list)  # {line, xy_a, xy_b, epipolar_error_px}


@dataclass(kw_only=True)
class ManualMatchesSummary:
    """--manual-matches: per pair given / kept and the rejected lines (rigsfm.run.matching.manual_merge)."""

    file: str = ""
    given: int = 0
    kept: int = 0
    pairs: list[ManualPairSummary] = field(default_factory=list)


@dataclass(kw_only=True)
class Summary:
    rigsfm_version: str = ""
    pycolmap_version: str = ""
    inputs: InputsSummary = field(default_factory=InputsSummary)
    options: dict = field(default_factory=dict)  # the RunOptions, as JSON
    metric: bool = False
    scale: ScaleSummary = field(default_factory=ScaleSummary)
    mapping: MappingSummary = field(default_factory=MappingSummary)
    registered: dict[str, Registration] = field(default_factory=dict)  # per sensor
    unregistered: list[str] = field(default_factory=list)
    num_points3D: int = 0
    mean_reprojection_error_px: float | None = None
    reprojection_error: dict[str, CameraError] = field(default_factory=dict)  # per camera <rig>/<sensor>
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    manual_matches: ManualMatchesSummary | None = None
    world: WorldSummary | None = None
    epipolar_self_check: SelfCheckSummary | None = None
    frame_offsets: FrameOffsetsSummary | None = None
    uncertainty: UncertaintySummary | None = None  # rigsfm.run.adjustment.uncertainty
    # per rig, its calibration refined or held at rigs.yaml's values and why (rigsfm.run.adjustment.decisions.hold_or_refine;
    # empty with --fixed-calibration)
    calibration_decisions: list[dict] = field(default_factory=list)
    # the tracks removed because each alone pulled the refined calibration (rigsfm.run.adjustment.adjust's
    # influential-track rule: removed, rounds, per_round, largest_kept, threshold, seconds); None: not scored
    influential_tracks: dict | None = None
    pairs: PairsSummary | None = None
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds per stage (all threads)
    narrow_observations: NarrowObservationsSummary | None = None  # --narrow (None: off)
    # what changed from the finished result this run replaced (rigsfm.run.deliver.changes_from); None: none replaced
    replaced: dict | None = None

    def to_json(self) -> dict:
        data = asdict(self)
        if self.world is not None:
            data["world"] = self.world.to_json()
        return data

    @classmethod
    def from_json(cls, data: dict) -> Summary:
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        for key, kind in (("inputs", InputsSummary), ("scale", ScaleSummary), ("mapping", MappingSummary)):
            if isinstance(values.get(key), dict):
                values[key] = _typed(kind, values[key])
        values["registered"] = {k: _typed(Registration, v) for k, v in (values.get("registered") or {}).items()}
        values["reprojection_error"] = {k: _typed(CameraError, v)
                                        for k, v in (values.get("reprojection_error") or {}).items()}
        if isinstance(values.get("pairs"), dict):
            pairs = _typed(PairsSummary, values["pairs"])
            pairs.missed = [_typed(MissedPairSummary, v) for v in pairs.missed or []]
            values["pairs"] = pairs
        if isinstance(values.get("frame_offsets"), dict):
            values["frame_offsets"] = _typed(FrameOffsetsSummary, values["frame_offsets"])
        if isinstance(values.get("uncertainty"), dict):
            uncertainty = _typed(UncertaintySummary, values["uncertainty"])
            uncertainty.narrow = {k: _typed(NarrowUncertaintySummary, v) for k, v in (uncertainty.narrow or {}).items()}
            uncertainty.pairs = [_typed(PairBandSummary, v) for v in uncertainty.pairs or []]
            values["uncertainty"] = uncertainty
        if isinstance(values.get("world"), dict):
            values["world"] = _typed(WorldSummary, values["world"])
        if isinstance(values.get("epipolar_self_check"), dict):
            values["epipolar_self_check"] = self_check_from_json(values["epipolar_self_check"])
        if isinstance(values.get("narrow_observations"), dict):
            values["narrow_observations"] = narrow_observations_from_json(values["narrow_observations"])
        if isinstance(values.get("manual_matches"), dict):
            values["manual_matches"] = manual_matches_from_json(values["manual_matches"])
        return cls(**values)

    @classmethod
    def read(cls, path: Path) -> Summary | None:
        """The summary at ``path``; None when there is none; a clear error when it is unreadable."""
        path = Path(path)
        if not path.is_file():
            return None
        try:
            return cls.from_json(json.loads(path.read_text(encoding="utf-8")))
        except (json.JSONDecodeError, UnicodeDecodeError, TypeError, AttributeError, ValueError) as error:
            raise WorkspaceError(f"{path} is not a valid summary ({error}); re-run `rigsfm run ... --overwrite`") \
                from None


def _typed(kind, values: dict):
    known = {f.name for f in fields(kind)}
    return kind(**{k: v for k, v in values.items() if k in known})


def self_check_from_json(data: dict) -> SelfCheckSummary:
    """A self-check record from its JSON (``summary.json``'s ``epipolar_self_check``)."""
    check = _typed(SelfCheckSummary, data)
    check.settings = _typed(SelfCheckSettings, data.get("settings") or {})
    check.pairs = [_typed(SelfCheckPairSummary, p) for p in data.get("pairs") or []]
    return check


def narrow_observations_from_json(data: dict) -> NarrowObservationsSummary:
    """A ``--narrow`` record from its JSON (``summary.json``'s ``narrow_observations``)."""
    record = _typed(NarrowObservationsSummary, data)
    record.pairs = [_typed(NarrowPairSummary, p) for p in data.get("pairs") or []]
    record.held_out_check = [_typed(HeldOutCheckSummary, c) for c in data.get("held_out_check") or []]
    return record


def manual_matches_from_json(data: dict) -> ManualMatchesSummary:
    """A --manual-matches record from its JSON (``summary.json``'s ``manual_matches``)."""
    record = _typed(ManualMatchesSummary, data)
    record.pairs = [_typed(ManualPairSummary, p) for p in data.get("pairs") or []]
    return record


def describe_self_check(check: SelfCheckSummary) -> str:
    """One line on a self-check record: the verdicts, and why pairs have none."""
    pairs = check.pairs
    if not pairs:
        return f"nothing checked: {check.skipped or 'no pair of synchronised narrow images'}"
    verdicts = [p.verdict for p in pairs]
    needed = check.settings.min_matches
    if all(v == "too few matches" for v in verdicts):
        most = max(p.matches for p in pairs)
        found = "0 matches in each" if most == 0 else f"at most {most} matches"
        return (f"none of the {len(pairs)} synchronised narrow pairs could be checked ({found}, {needed} needed): "
                "featureless narrow views, as expected in a homogeneous scene; the bands are the model's alone")
    line = f"{verdicts.count('ok')} ok, {verdicts.count('failed')} failed"
    rest = [v for v in verdicts if v not in ("ok", "failed")]
    if rest:
        why = {"too few matches": f"fewer than {needed} matches (featureless views)",
               "not synchronised": "not synchronised (a rig's frames are off in time)",
               "inconclusive": "inconclusive (matches fill even the widest search)", "no band": "no band"}
        line += f", {len(rest)} without verdict: " + ", ".join(
            f"{rest.count(v)} {why.get(v, v)}" for v in sorted(set(rest), key=rest.index))
    return line
