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


@dataclass(kw_only=True)
class PairBandSummary:
    """One narrow pair's 95 % epipolar band (rigsfm.run.adjustment.bands.PairBand)."""

    i: str = ""
    j: str = ""
    band_px: float | None = None
    points: str | None = None  # floor or depths
    predicted_below_85: float | None = None  # the model's probability that < 85 % of this pair's points are inside


@dataclass(kw_only=True)
class UncertaintySummary:
    calibration: str = "fixed"  # refine or fixed (rigsfm.run.options.Calibration)
    covariance: str | None = None  # posterior (refine) or consider (fixed); None when it could not be estimated
    pixel_sigma_px: float | None = None  # the images' weighting noise per coordinate (estimated x inflation)
    floor: str = "none"  # where the bands' analysis points lie: known_lengths, points, none (depths)
    bands: str = "linear"  # linear in the covariance, or sampled (re-adjusted over calibration draws: <= 3 rigs)
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
    manual_matches: dict | None = None  # rigsfm.run.matching.manual_merge.manual_matches_summary
    world: dict | None = None  # the result's frame and its floor fit (rigsfm.run.world.frame.WorldResult.to_dict)
    epipolar_self_check: dict | None = None  # rigsfm.run.checks.self_check.SelfCheck.to_dict
    frame_offsets: FrameOffsetsSummary | None = None
    uncertainty: UncertaintySummary | None = None  # rigsfm.run.adjustment.uncertainty
    # per rig, its calibration refined or held at rigs.yaml's values and why (rigsfm.run.adjustment.decisions.hold_or_refine;
    # empty with --fixed-calibration)
    calibration_decisions: list[dict] = field(default_factory=list)
    pairs: PairsSummary | None = None
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds per stage (all threads)
    narrow_observations: dict | None = None  # --narrow: decided, used, held-out check (rigsfm.run.narrow)

    def to_json(self) -> dict:
        return asdict(self)

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


def describe_self_check(check: dict) -> str:
    """One line on a self-check record (``SelfCheck.to_dict``): the verdicts, and why pairs have none."""
    pairs = check.get("pairs") or []
    if not pairs:
        return f"nothing checked: {check.get('skipped') or 'no pair of synchronised narrow images'}"
    verdicts = [p["verdict"] for p in pairs]
    needed = (check.get("settings") or {}).get("min_matches", SELF_CHECK_MIN_MATCHES)
    if all(v == "too few matches" for v in verdicts):
        most = max(p.get("matches", 0) for p in pairs)
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
