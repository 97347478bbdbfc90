"""Repeated views: a static rig sees the same background in every frame, so its keypoints there err alike.

A point observed by one camera (one rig sensor) in ``n`` frames gives ``n`` reprojection residuals whose keypoint
errors share a part: the detector's error on the same texture under the same view repeats, only the image noise
differs. Counted as independent they carry ``n`` times the information of one view; with errors of equal variance
and correlation ``rho`` the ``n`` carry ``n / (1 + (n - 1) rho)`` (the information of their mean). The covariance
weighs each such residual by ``1 / sqrt(1 + (n - 1) rho)``.

``rho`` per camera: the images are weighted as if their error were ``pixel_sigma_inflation`` times the noise the
residuals show, the excess being the keypoints' systematic error between views far apart; that excess repeats
exactly in a static camera's views, and of the noise itself the share ``rho_noise`` does (1 minus the keypoints'
spread about their group's mean over the noise). So ``rho = 1 - (1 - rho_noise) / inflation^2``. A camera whose
repeated keypoints scatter more than the noise (a rig that moved between frames: its views differ) is not a
repeated view and keeps its full weight."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap
import scipy.sparse as sp

from rigsfm.run.adjustment.model import estimate_pixel_sigma

logger = logging.getLogger(__name__)


def _groups(reconstruction: pycolmap.Reconstruction) -> dict[int, list[np.ndarray]]:
    """Per camera: per point it observes in at least two frames, the keypoints (n x 2, px). A static camera's views
    project the point to the same pixel, so their scatter is that of the keypoint errors' own parts."""
    out: dict[int, list[np.ndarray]] = {}
    for point in reconstruction.points3D.values():
        by_camera: dict[int, list[np.ndarray]] = {}
        for element in point.track.elements:
            image = reconstruction.image(element.image_id)
            if image.has_pose:
                by_camera.setdefault(image.camera_id, []).append(np.asarray(image.points2D[element.point2D_idx].xy))
        for camera_id, keypoints in by_camera.items():
            if len(keypoints) >= 2:
                out.setdefault(camera_id, []).append(np.array(keypoints))
    return out


def repeated_view_noise_correlation(reconstruction: pycolmap.Reconstruction,
                                    max_error_px: float | None = None) -> dict[int, float]:
    """Per camera with repeated views of points whose keypoints scatter no more than the images' noise
    (``estimate_pixel_sigma``; ``max_error_px`` as there): the correlation of their noise, 1 minus that scatter
    (about each group's mean, its degrees of freedom counted) over the noise. Cameras that moved are left out."""
    groups = _groups(reconstruction)
    if not groups:
        return {}
    noise = estimate_pixel_sigma(reconstruction, max_error_px) ** 2
    if noise <= 1e-12:  # exact keypoints: nothing to weigh
        return {}
    out = {}
    for camera_id, camera_groups in groups.items():
        within = (sum(float(np.sum((g - g.mean(axis=0)) ** 2)) for g in camera_groups)
                  / sum(2 * (len(g) - 1) for g in camera_groups))
        if within <= noise:
            out[camera_id] = 1.0 - within / noise
    return out


def repeated_view_correlation(reconstruction: pycolmap.Reconstruction, inflation: float,
                              max_error_px: float | None = None) -> dict[int, float]:
    """Per camera with repeated views: ``rho`` of the images' weighting error (module docstring)."""
    return {camera_id: 1.0 - (1.0 - rho) / inflation**2
            for camera_id, rho in repeated_view_noise_correlation(reconstruction, max_error_px).items()}


def repeated_view_weights(jacobian: sp.csr_matrix, num_a: int, camera_of_column: np.ndarray,
                          rho: dict[int, float]) -> np.ndarray:
    """Per row of ``jacobian`` (columns: ``num_a`` non-point parameters, then 3 per point): the weight
    ``1 / sqrt(1 + (n - 1) rho)`` of a reprojection residual whose point its camera observes ``n`` times, ``rho``
    that camera's (1 elsewhere, for cameras without one, and where no column names the camera).
    ``camera_of_column``: camera id per non-point column, -1 for others."""
    num_rows = jacobian.shape[0]
    weights = np.ones(num_rows)
    if not rho or num_rows == 0 or num_a == 0:
        return weights
    rows = np.repeat(np.arange(num_rows), np.diff(jacobian.indptr))
    columns = jacobian.indices
    point_of = np.where(columns >= num_a, (columns - num_a) // 3, -1)
    camera_of = np.where(columns < num_a, camera_of_column[np.minimum(columns, num_a - 1)], -1)
    row_point = np.full(num_rows, -1)
    row_camera = np.full(num_rows, -1)
    np.maximum.at(row_point, rows, point_of)
    np.maximum.at(row_camera, rows, camera_of)
    row_rho = np.array([rho.get(int(c), 0.0) for c in row_camera])
    keyed = np.flatnonzero((row_point >= 0) & (row_camera >= 0) & (row_rho > 0))
    if keyed.size == 0:
        return weights
    keys = row_point[keyed].astype(np.int64) * (int(row_camera.max()) + 1) + row_camera[keyed]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    n = counts[inverse] / 2.0  # two rows per observation
    weights[keyed] = 1.0 / np.sqrt(1.0 + (np.maximum(n, 1.0) - 1.0) * row_rho[keyed])
    return weights
