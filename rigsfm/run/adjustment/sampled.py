"""The band of a small network by re-adjusting it over draws of its calibration, without linearising."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap
from scipy.special import ndtr

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.geometry import Plane, epipolar_lines, line_distances
from rigsfm.core.names import registered_narrow_images
from rigsfm.run.adjustment.bands import BAND_PROBABILITY, PairBand, PairModel, band_points
from rigsfm.run.adjustment.covariance import joint_covariance
from rigsfm.run.adjustment.priors import calibration_priors, draw_calibration
from rigsfm.run.adjustment.result import AdjustResult

logger = logging.getLogger(__name__)


def distances_under(estimate: pycolmap.Reconstruction, draw: pycolmap.Reconstruction, name_i: str, name_j: str,
                    pixels_i: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """The band's quantity without linearisation: distances (pinhole px of j) from the estimated epipolar lines of
    the correspondences that ``draw`` (a possible truth: its narrow cameras and relative pose) gives the analysis
    points (``pixels_i`` of image i at ``depths`` in camera i); NaN where a point falls behind camera j."""
    est_i, est_j = (estimate.find_image_with_name(n) for n in (name_i, name_j))
    drawn_i, drawn_j = (draw.find_image_with_name(n) for n in (name_i, name_j))
    camera_i, camera_j = estimate.cameras[est_i.camera_id], estimate.cameras[est_j.camera_id]
    rays = np.asarray(draw.cameras[drawn_i.camera_id].cam_from_img(pixels_i))
    x_i = np.column_stack([rays, np.ones(len(rays))]) * depths[:, None]
    x_j = np.asarray((drawn_j.cam_from_world() * drawn_i.cam_from_world().inverse()) * x_i)
    out = np.full(len(x_i), np.nan)
    front = x_j[:, 2] > 0
    seen = np.asarray(camera_j.cam_from_img(np.asarray(draw.cameras[drawn_j.camera_id].img_from_cam(x_j[front]))))
    lines = epipolar_lines(camera_i, camera_j, est_j.cam_from_world() * est_i.cam_from_world().inverse(), pixels_i)
    out[front] = line_distances(camera_j, lines[front], np.column_stack([seen, np.ones(len(seen))]))
    return out


def pooled_shifted_quantile(shifts: np.ndarray, sigmas: np.ndarray, probability: float = BAND_PROBABILITY) -> float:
    """``b`` with ``mean P(|shift + N(0, sigma^2)| <= b) = probability`` over all entries (bisection)."""
    sigmas = np.where(sigmas > 0, sigmas, 1e-12)
    low, high = 0.0, float(np.max(np.abs(shifts) + 6.0 * sigmas))
    for _ in range(50):
        middle = 0.5 * (low + high)
        inside = ndtr((middle - shifts) / sigmas) - ndtr((-middle - shifts) / sigmas)
        if np.mean(inside) < probability:
            low = middle
        else:
            high = middle
    return high


def sampled_pair_bands(result: AdjustResult, plane: Plane | None, num_draws: int = 40,
                       seed: int = 0) -> dict[tuple[str, str], PairBand]:
    """The band of a small network without linearising the calibration's effect: ``num_draws`` times, rigs.yaml
    moved by a draw of its priors and the network adjusted again (from the estimate; with priors centred on the
    draw when refining, as in "randomise then optimise", but with the images weighted as below); each draw's exact
    distances plus the image noise's own (linear, Gaussian) spread, pooled. The relative pose of two rigs can
    answer a calibration error far from linearly.

    Each draw weighs the images by the noise of its own starting residuals (the estimate's poses under the drawn
    calibration, far larger than the estimate's), not by the estimate's: the images then hold the draws back less
    than the estimate's posterior would, and the band covers as it says (see benchmarks/README.md, "The sampled
    band against the linear one on rendered 3-rig networks")."""
    from dataclasses import replace

    from rigsfm.run.adjustment.adjust import adjust

    estimate = result.reconstruction
    image_covariance = joint_covariance(result, image_only=True)
    rng = np.random.default_rng(seed)
    draws = []
    options = replace(result.options, max_rounds=1)  # from the estimate, its outliers already gone: one solve
    priors = result.priors or calibration_priors(result.rigs)
    for _ in range(num_draws):
        try:
            draws.append(adjust(estimate, draw_calibration(result.rigs, priors, rng), result.scale_spec, options,
                                result.priors, with_covariance=False, held_rigs=result.held_rigs,
                                point_sigmas=result.point_sigmas).reconstruction)
        except ReconstructionError as error:
            logger.info("A calibration draw failed to adjust: %s", error)
    images = {im.name: im for im in registered_narrow_images(estimate)}
    names = sorted(images)
    bands = {}
    for k, name_i in enumerate(names):
        for name_j in names[k + 1:]:
            pixels, depths, kind = band_points(estimate, images[name_i], images[name_j], plane)
            if len(pixels) == 0 or not draws:
                continue
            shifts = np.array([distances_under(estimate, draw, name_i, name_j, pixels, depths) for draw in draws])
            shifts = np.where(np.isfinite(shifts), shifts, 1e6)  # behind camera j: outside any band
            if image_covariance is not None:
                model = PairModel(estimate, image_covariance, images[name_i], images[name_j], {})
                jac = model.jacobian(pixels, depths)
                sigmas = np.sqrt(np.clip(np.einsum("pk,kl,pl->p", jac, model.covariance, jac), 0.0, None))
            else:
                sigmas = np.zeros(len(pixels))
            sigmas = np.broadcast_to(sigmas, shifts.shape)
            band = pooled_shifted_quantile(shifts, sigmas)
            inside = ndtr((band - shifts) / np.maximum(sigmas, 1e-12)) - ndtr((-band - shifts) / np.maximum(sigmas, 1e-12))
            bands[(name_i, name_j)] = PairBand(band, kind, len(pixels), (float(depths.min()), float(depths.max())),
                                               inside.mean(axis=1))
    return bands
