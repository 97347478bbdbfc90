"""Do scale.yaml's measurements agree on the scale of the mapped model? (a plausibility check before the adjustment)

Each measurement i (a camera distance or a known length) of M_i metres has a length L_i in the mapped model,
so it implies M_i / L_i metres per model unit. Measurements of one network imply one scale: a distance written in
millimetres, centimetres or feet implies 1000x, 100x or 3.3x the others' scale and, weighted by its small sigma,
would drag the whole adjustment (and make the uncertainty stage take minutes) before the run ended with residuals
no one can read. :func:`check_scale_agreement` compares each measurement's scale with the median of the others' and
refuses, in one line naming them and the fix, those off by more than :data:`PLAUSIBLE_FACTOR` beyond their sigmas.
Without a majority (two measurements, or no group holding most) the odd one cannot be named, and the mapped model
itself may be wrong (two rigs registered from weak matches): only a disagreement of :data:`UNDECIDED_FACTOR` or
more is refused, a smaller one is logged and left to the adjustment's warnings.

The mapped model is the mapper's, before the adjustment: its shape is good where rigs share points (its errors are
percent, far inside the factor) but open for rigs tied loosely to the rest, whose distances the adjustment settles
with the measurements themselves. Distances to such rigs are left out here, as are measurements the mapped model
cannot hold (unregistered cameras, a bar seen in fewer than two registered images). A narrow camera's centre is its
rig's wide centre, with the rig's baseline |t| added to the distance's uncertainty.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.scale import UnusableMeasurement, camera_centre, known_length_in_model
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.mapping.ties import loosely_tied_rigs

# Beyond their sigmas, measurements of one network may imply scales this far apart in the mapped model before they
# are refused: the mapper's shape errors between well-tied rigs are percent; unit mistakes are 3.3x (feet), 10x and
# more.
logger = logging.getLogger(__name__)

PLAUSIBLE_FACTOR = 2.0
SIGMAS = 3.0
# Without a majority to name the odd one out, a disagreement may as well be the mapped model's (a pair registered
# wrongly from weak matches, which the adjustment's own checks then report): only one of a unit mistake's size
# (millimetres, centimetres, inches) is refused.
UNDECIDED_FACTOR = 10.0


@dataclass(frozen=True)
class _Implied:
    label: str
    meters: float
    model_length: float
    relative_sigma: float  # of meters / model_length

    @property
    def log_scale(self) -> float:
        return math.log(self.meters / self.model_length)


def _wide_end(camera: str, rigs: dict[str, RigCalibration]) -> tuple[str, float]:
    """``<rig>/<sensor>[/<file>]`` -> the name whose centre the mapped model holds (the wide camera's: the mapper
    poses wide images), and how far (metres) the named camera's centre may lie from it."""
    parts = camera.split("/")
    if len(parts) >= 2 and parts[1] == "narrow":
        rig = rigs.get(parts[0])
        baseline = float(np.linalg.norm(rig.narrow_from_wide.translation)) if rig is not None else 0.0
        return f"{parts[0]}/wide", baseline
    return camera, 0.0


def implied_scales(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec,
                   rigs: Sequence[RigCalibration]) -> list[_Implied]:
    """The measurements the mapped model holds, each with the scale it implies and that scale's relative sigma."""
    by_name = {rig.name: rig for rig in rigs}
    loose = set(loosely_tied_rigs(reconstruction))
    implied = []
    for i, d in enumerate(spec.camera_distances):
        (a, slack_a), (b, slack_b) = _wide_end(d.a, by_name), _wide_end(d.b, by_name)
        if {a.split("/")[0], b.split("/")[0]} & loose:
            continue
        try:
            length = float(np.linalg.norm(camera_centre(reconstruction, a) - camera_centre(reconstruction, b)))
        except UnusableMeasurement:
            continue
        if length <= 0.0:
            continue
        sigma = math.hypot(d.sigma, slack_a + slack_b) / d.meters
        implied.append(_Implied(f"camera_distance[{i}] ('{d.a}' - '{d.b}', {d.meters:g} m)", d.meters, length, sigma))
    for i, item in enumerate(spec.known_lengths):
        try:
            length, model_sigma = known_length_in_model(reconstruction, item, spec.pixel_sigma)
        except UnusableMeasurement:
            continue
        if length <= 0.0 or not math.isfinite(length):
            continue
        sigma = math.hypot(item.sigma / item.meters, model_sigma / length)
        implied.append(_Implied(f"known_length[{i}] ({item.meters:g} m)", item.meters, length, sigma))
    return implied


def _times(ratio: float) -> str:
    """``ratio`` in words a unit mistake is recognised by: 1000x, 3.3x, 1/1000."""
    big = ratio if ratio >= 1.0 else 1.0 / ratio
    words = f"{big:.0f}" if big >= 10.0 else f"{big:.2g}"
    return f"{words}x" if ratio >= 1.0 else f"1/{words}"


def _agree(a: _Implied, b: _Implied) -> bool:
    tolerance = math.log(PLAUSIBLE_FACTOR) + SIGMAS * math.log1p(a.relative_sigma + b.relative_sigma)
    return abs(a.log_scale - b.log_scale) <= tolerance


def check_scale_agreement(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec,
                          rigs: Sequence[RigCalibration]) -> None:
    """Refuse (``InputError``, one line) measurements whose scale in the mapped model disagrees with the others'
    by more than :data:`PLAUSIBLE_FACTOR` beyond :data:`SIGMAS` of their uncertainties: those outside the largest
    group that agree with one another when it holds most of them, else all, and then only when they are
    :data:`UNDECIDED_FACTOR` or more apart; nothing with fewer than two measurements the model holds."""
    implied = implied_scales(reconstruction, spec, rigs)
    if len(implied) < 2:
        return
    groups = [[o for o in implied if _agree(m, o)] for m in implied]
    group = max(groups, key=len)
    if len(group) == len(implied):
        return
    fix = "in other units than metres (millimetres, feet) or measures other points: fix it, or remove it"
    if 2 * len(group) > len(implied):  # most agree: the others are the odd ones out
        reference = float(np.median([m.log_scale for m in group]))
        parts = []
        for m in implied:
            if m not in group:
                ratio = math.exp(m.log_scale - reference)
                parts.append(f"{m.label} is {_times(ratio)} what the other {len(group)} measurement(s) give in the "
                             f"mapped model ({m.meters / ratio:.4g} m)")
        raise InputError(f"{spec.path}: {'; '.join(parts)}: a unit mistake (millimetres, feet) or other end points? "
                         "Give it in metres between the points named, or remove it")
    spread = math.exp(max(m.log_scale for m in implied) - min(m.log_scale for m in implied))
    if spread < UNDECIDED_FACTOR:
        logger.warning("%s: %s disagree on the scale by up to %s in the mapped model: left to the adjustment, whose "
                       "warnings say which (a wrong pose or a measurement off)", spec.path,
                       ", ".join(m.label for m in implied), _times(spread))
        return
    if len(implied) == 2:
        first, second = implied
        ratio = math.exp(first.log_scale - second.log_scale)
        raise InputError(f"{spec.path}: {first.label} and {second.label} disagree on the scale by {_times(ratio)} in "
                         f"the mapped model (by the second, the first would be {first.meters / ratio:.4g} m): one is "
                         f"{fix}")
    raise InputError(f"{spec.path}: {', '.join(m.label for m in implied)} disagree on the scale by up to "
                     f"{_times(spread)} in the mapped model, no group of them agreeing: one or more is {fix}")


# A known length lies level on the floor (README): its ends' heights along the cameras' up differ by the up's error
# only (synthetic rings of 3-8 rigs with 2 deg rolls: at most 6.6 % of its length, benchmarks/README.md); a bar
# marked with a and b swapped in one image differs by more (13 % on a rendered 6-rig crowd).
LEVEL_TOLERANCE = 0.08


def unlevel_known_lengths(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec | None) -> list[str]:
    """``SCALE MARKER`` warnings for the known lengths of ``spec`` whose ends, triangulated in ``reconstruction``,
    differ in height along the cameras' up by more than :data:`LEVEL_TOLERANCE` of their length: other points
    marked in one image, most often a and b swapped. Such a bar triangulates at another length along the epipolar
    lines without a pixel residual, so the adjustment meets its length at a wrong scale and no residual says it. Only
    where the cameras' x axes give the up (the -y fallback is off by their pitch)."""
    from rigsfm.run.adjustment.scale import triangulate_observed_point
    from rigsfm.run.world.floor_model import posed_images, up_prior

    if spec is None or not spec.known_lengths or not posed_images(reconstruction):
        return []
    up, source = up_prior(reconstruction)
    if source != "camera x axes":
        return []
    warnings = []
    for i, item in enumerate(spec.known_lengths):
        ends = [triangulate_observed_point(reconstruction, [(o.image, np.asarray(getattr(o, end), dtype=np.float64))
                                                            for o in item.observations]) for end in ("a", "b")]
        if ends[0] is None or ends[1] is None:
            continue  # fewer than two registered images: the adjustment names it as unused
        length = float(np.linalg.norm(ends[0] - ends[1]))
        slope = abs(float((ends[0] - ends[1]) @ up)) / length if length > 0 else 0.0
        if slope > LEVEL_TOLERANCE:
            images = ", ".join(o.image for o in item.observations)
            warning = (f"SCALE MARKER: known_length[{i}] ({item.meters:g} m): its ends differ in height by "
                       f"{100 * slope:.0f} % of its length, but a known length lies level on the floor: a and b "
                       f"swapped (or other points marked) in one of {images}, which makes the adjustment meet its "
                       f"length at a wrong scale with no residual to show it; fix its pixels in {spec.path}")
            logger.warning(warning)
            warnings.append(warning)
    return warnings
