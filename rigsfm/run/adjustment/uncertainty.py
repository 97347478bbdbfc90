"""Stage 8, uncertainty: what the result is worth: the joint covariance of rig poses and calibration (``covariance``), each
narrow camera's uncertainty (``narrow``), and the 95 % epipolar band of every narrow pair: linear in the
covariance (``bands``), or re-adjusted over calibration draws for small networks (``sampled``)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.geometry import Plane
from rigsfm.core.names import name_of
from rigsfm.core.summary import BANDS_WIDE_ONLY
from rigsfm.run.adjustment.bands import PairBand, narrow_pair_bands
from rigsfm.run.adjustment.covariance import joint_covariance
from rigsfm.run.adjustment.model import sensor_from_rig_view
from rigsfm.run.adjustment.narrow import NarrowUncertainty, narrow_uncertainty
from rigsfm.run.adjustment.result import AdjustResult, JointCovariance
from rigsfm.run.adjustment.sampled import sampled_pair_bands
from rigsfm.run.options import Calibration

logger = logging.getLogger(__name__)


@dataclass
class Uncertainty:
    covariance: JointCovariance | None
    narrow: dict[str, NarrowUncertainty]
    bands: dict[tuple[str, str], PairBand]
    floor: str  # where the band's analysis points come from: floor_fit (the world stage), known_lengths, points, none
    seconds: dict[str, float]
    sampled: bool = False  # bands re-adjusted over calibration draws (sampled_pair_bands), not linear
    bands_from: str = BANDS_WIDE_ONLY  # the adjustment: BANDS_WITH_NARROW for the second one


# Networks this small get the sampled band (sampled_pair_bands): there the linear band covers less than it says
# (see benchmarks/README.md and benchmarks/three_rig_bands.py).
SAMPLED_BAND_MAX_FRAMES = 3


def estimate_uncertainty(result: AdjustResult, num_samples: int = 400, seed: int = 0,
                         sampled: bool | None = None, floor: Plane | None = None,
                         floor_source: str | None = None) -> Uncertainty:
    """The joint covariance (reused from ``result`` when the adjustment computed it), every narrow camera's
    uncertainty and every overlapping pair's band: linear (``narrow_pair_bands``), or re-adjusted over
    calibration draws (``sampled_pair_bands``; default for networks of at most ``SAMPLED_BAND_MAX_FRAMES``
    registered frames). The bands' analysis points lie on ``floor`` (in ``result.reconstruction``'s frame) when
    given, ``floor_source`` saying where it comes from (default ``floor_fit``, the world stage's floor fit; or
    ``rigsfm.run.world.analysis_floor.find_floor``'s ``known_lengths`` or ``points``); without it, at every depth.
    ``result`` is not modified."""
    start = time.perf_counter()
    covariance = result.covariance
    if covariance is None:
        try:
            covariance = joint_covariance(result)
        except ReconstructionError as error:
            logger.warning("No joint covariance: %s", error)
    seconds = {"covariance": covariance.seconds if covariance is not None else time.perf_counter() - start}
    if covariance is None:
        return Uncertainty(None, {}, {}, "none", seconds)
    start = time.perf_counter()
    narrow = narrow_uncertainty(result.reconstruction, covariance)
    plane = floor
    floor_source = "none" if floor is None else floor_source or "floor_fit"
    if sampled is None:
        sampled = result.reconstruction.num_reg_frames() <= SAMPLED_BAND_MAX_FRAMES
    if sampled:
        bands = sampled_pair_bands(result, plane, seed=seed)
    else:
        bands = narrow_pair_bands(result.reconstruction, covariance, plane=plane, num_samples=num_samples, seed=seed)
    seconds["bands"] = time.perf_counter() - start
    logger.info("Uncertainty: covariance %.1f s, %d %s bands %.1f s", seconds["covariance"], len(bands),
                "sampled" if sampled else "linear", seconds["bands"])
    return Uncertainty(covariance, narrow, bands, floor_source, seconds, sampled)


def calibration_changes(result: AdjustResult, covariance: JointCovariance | None, metric: bool = True
                        ) -> dict[str, dict]:
    """Per camera ``<rig>/<sensor>`` with refined intrinsics: focal and principal-point change from rigs.yaml and
    their posterior sigma; per narrow camera also E^sl's rotation (deg) and translation (mm; not ``metric``: in the
    mapping unit, ``_units`` keys, the ``_mm`` ones null) change and sigma. Empty for a fixed calibration."""
    per_metre, unit = (1000.0, "mm") if metric else (1.0, "units")
    if result.calibration != Calibration.REFINE:
        return {}
    rec = result.reconstruction
    by_name = {rig.name: rig for rig in result.rigs}
    out = {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        name = name_of(image)
        if not image.has_pose or name.camera in out or name.rig not in by_name:
            continue
        camera = rec.cameras[image.camera_id]
        before = by_name[name.rig].camera(name.sensor)
        row: dict[str, float | None] = {"focal_change_percent": 100.0 * (camera.mean_focal_length() / before.mean_focal_length() - 1.0),
               "principal_point_change_px": float(np.hypot(camera.principal_point_x - before.principal_point_x,
                                                           camera.principal_point_y - before.principal_point_y))}
        key = ("camera", image.camera_id)
        row["observed"] = bool(covariance is not None and key in covariance.offsets and key not in covariance.prior_only)
        if name.is_narrow:
            frame = rec.frame(image.frame_id)
            sensor = sensor_from_rig_view(rec, frame.rig_id, camera.sensor_id)
            prior = by_name[name.rig].narrow_from_wide
            delta = sensor.rotation * prior.rotation.inverse()
            row["narrow_from_wide_rotation_change_deg"] = float(np.degrees(delta.angle()))
            if not metric:
                row["narrow_from_wide_translation_change_mm"] = row["narrow_from_wide_translation_sigma_mm"] = None
            row[f"narrow_from_wide_translation_change_{unit}"] = per_metre * float(
                np.linalg.norm(np.asarray(sensor.translation) - np.asarray(prior.translation)))
            sensor_key = ("sensor_from_rig", image.camera_id)
            if covariance is not None and sensor_key in covariance.offsets:
                sigma = covariance.sigma(sensor_key)
                row["narrow_from_wide_rotation_sigma_deg"] = float(np.degrees(np.linalg.norm(sigma[:3])))
                row[f"narrow_from_wide_translation_sigma_{unit}"] = per_metre * float(np.linalg.norm(sigma[3:]))
        out[name.camera] = row
    return out


def uncertainty_summary(result: AdjustResult, uncertainty: Uncertainty, metric: bool = True):
    """The summary.json record of the uncertainty stage (``rigsfm.core.summary.UncertaintySummary``); not ``metric``:
    the centres' values in the mapping unit (``_units`` keys), their ``_mm`` keys null."""
    from rigsfm.core.summary import NarrowUncertaintySummary, PairBandSummary, UncertaintySummary

    def narrow(u) -> NarrowUncertaintySummary:
        covariance = None if u.centre_covariance_mm2 is None else [list(r) for r in u.centre_covariance_mm2]
        record = NarrowUncertaintySummary(
            rotation_sigma_deg=u.rotation_sigma_deg,
            rotation_covariance_deg2=None if u.rotation_covariance_deg2 is None
            else [list(r) for r in u.rotation_covariance_deg2])
        if metric:
            record.centre_sigma_mm, record.centre_covariance_mm2 = u.centre_sigma_mm, covariance
        else:  # the adjustment's 'mm' are the mapping unit's thousandths
            record.centre_sigma_units = u.centre_sigma_mm / 1000.0
            record.centre_covariance_units2 = None if covariance is None else [[v / 1e6 for v in r] for r in covariance]
        return record

    covariance = uncertainty.covariance
    return UncertaintySummary(
        calibration=str(result.calibration),
        covariance=None if covariance is None else covariance.kind,
        pixel_sigma_px=None if covariance is None else covariance.pixel_sigma,
        floor=uncertainty.floor,
        bands="sampled" if uncertainty.sampled else "linear",
        bands_from=uncertainty.bands_from,
        narrow={name: narrow(u) for name, u in uncertainty.narrow.items()},
        pairs=[PairBandSummary(i=i, j=j, band_px=b.band_px, points=b.points, predicted_below_85=b.predicted_below_85)
               for (i, j), b in sorted(uncertainty.bands.items())],
        refined_calibration=calibration_changes(result, covariance, metric),
    )
