"""Two-view geometry measures on calibrated cameras: epipolar (Sampson) error and planarity."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

Config = pycolmap.TwoViewGeometryConfiguration
PLANAR = (Config.PLANAR, Config.PANORAMIC, Config.PLANAR_OR_PANORAMIC)  # a homography explains the matches
POSED = (Config.CALIBRATED, Config.UNCALIBRATED, *PLANAR)  # configurations that carry a relative pose


def sampson_error_px(
    essential: np.ndarray, cam1: pycolmap.Camera, cam2: pycolmap.Camera, xy1: np.ndarray, xy2: np.ndarray
) -> np.ndarray:
    """Sampson epipolar error of each correspondence (``x2^T E x1 = 0``), in pixels via the mean focal."""
    x1 = np.c_[np.asarray(cam1.cam_from_img(np.asarray(xy1, np.float64))), np.ones(len(xy1))]
    x2 = np.c_[np.asarray(cam2.cam_from_img(np.asarray(xy2, np.float64))), np.ones(len(xy2))]
    ex1, etx2 = x1 @ essential.T, x2 @ essential
    num = np.sum(x2 * ex1, axis=1) ** 2
    den = ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2
    focal = 0.5 * (cam1.mean_focal_length() + cam2.mean_focal_length())
    return np.sqrt(num / np.maximum(den, 1e-300)) * focal


def planar_fraction(
    cam1: pycolmap.Camera, cam2: pycolmap.Camera, xy1: np.ndarray, xy2: np.ndarray, max_error_px: float
) -> float:
    """Share of the correspondences one homography explains, on undistorted normalised coordinates.

    Near 1 means the points lie on one plane (or the cameras share a centre): the relative pose is then
    ambiguous. Computed after undistortion because lens distortion bends a plane's image away from
    any homography in raw pixels (COLMAP's own H test runs on raw pixels and misses this).
    """
    if len(xy1) < 4:
        return 1.0
    n1 = np.asarray(cam1.cam_from_img(np.asarray(xy1, np.float64)))
    n2 = np.asarray(cam2.cam_from_img(np.asarray(xy2, np.float64)))
    threshold = max_error_px / cam2.mean_focal_length()
    best = 0
    for method in (cv2.RANSAC, cv2.LMEDS):  # RANSAC's 4-point samples are unstable on thin strips
        h, _ = cv2.findHomography(n1, n2, method, threshold, maxIters=2000, confidence=0.999)
        if h is not None:
            mapped = np.c_[n1, np.ones(len(n1))] @ h.T
            with np.errstate(divide="ignore", invalid="ignore"):
                residual = np.linalg.norm(mapped[:, :2] / mapped[:, 2:] - n2, axis=1)
            best = max(best, int(np.sum(residual < threshold)))
    return best / len(xy1)
