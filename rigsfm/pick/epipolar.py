"""Epipolar geometry of the pairs picked so far: normalised 8-point, made robust by a small RANSAC.

Without intrinsics the fundamental matrix F (``x_b^T F x_a = 0``, COLMAP pixels) is estimated from the
pixel coordinates (Hartley normalisation). With the calibrated wide cameras (``--rigs``) the points are
first undistorted and the essential matrix is estimated by COLMAP's 5-point LO-RANSAC (far more
stable than a linear 8-point E for a few clicks); epipolar "lines" are then curves in the distorted
image and are returned as polylines. Every residual is a Sampson distance in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.geometry import project, sampson

MIN_PAIRS = 8


def _normalise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley: centroid at 0, mean distance sqrt(2); returns homogeneous points and the 3x3 transform."""
    centre = points.mean(axis=0)
    scale = np.sqrt(2.0) / max(float(np.mean(np.linalg.norm(points - centre, axis=1))), 1e-12)
    t = np.array([[scale, 0, -scale * centre[0]], [0, scale, -scale * centre[1]], [0, 0, 1]])
    return np.c_[points, np.ones(len(points))] @ t.T, t


def eight_point(xa: np.ndarray, xb: np.ndarray, essential: bool = False) -> np.ndarray:
    """Normalised 8-point estimate of F, ``x_b^T F x_a = 0`` (Hartley normalisation, rank 2 enforced).

    With ``essential`` the inputs are normalised camera coordinates (already well conditioned): the
    linear solution is projected onto the essential matrices (singular values 1, 1, 0) directly.
    """
    xa, xb = np.asarray(xa, np.float64), np.asarray(xb, np.float64)
    if essential:
        pa, ta = np.c_[xa, np.ones(len(xa))], np.eye(3)
        pb, tb = np.c_[xb, np.ones(len(xb))], np.eye(3)
    else:
        (pa, ta), (pb, tb) = _normalise(xa), _normalise(xb)
    a = np.einsum("ni,nj->nij", pb, pa).reshape(len(pa), 9)
    m = np.linalg.svd(a)[2][-1].reshape(3, 3)
    u, s, vt = np.linalg.svd(m)
    s = np.array([1.0, 1.0, 0.0]) if essential else np.array([s[0], s[1], 0.0])
    m = tb.T @ (u @ np.diag(s) @ vt) @ ta
    return m / np.linalg.norm(m)


def robust_eight_point(
    xa: np.ndarray,
    xb: np.ndarray,
    threshold: float,
    essential: bool = False,
    iterations: int = 500,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """8-point inside RANSAC (a few gross errors must not bend the lines), refit on the inliers."""
    n = len(xa)
    best = np.ones(n, dtype=bool)
    if n > MIN_PAIRS:
        rng = np.random.default_rng(seed)
        best_count = -1
        for _ in range(iterations):
            sample = rng.choice(n, MIN_PAIRS, replace=False)
            inliers = np.abs(sampson(eight_point(xa[sample], xb[sample], essential), xa, xb)) < threshold
            if inliers.sum() > best_count:
                best, best_count = inliers, int(inliers.sum())
        if best.sum() < MIN_PAIRS:
            best = np.ones(n, dtype=bool)
    return eight_point(xa[best], xb[best], essential), best


@dataclass
class EpipolarModel:
    """The current two-view model: F in pixels, or E with the two calibrated cameras."""

    matrix: np.ndarray
    camera_a: pycolmap.Camera | None = None
    camera_b: pycolmap.Camera | None = None

    @property
    def calibrated(self) -> bool:
        return self.camera_a is not None

    def _normalised(self, xy: np.ndarray | tuple[float, float], side: str) -> np.ndarray:
        camera = self.camera_a if side == "a" else self.camera_b
        # a model's images have cameras
        return np.asarray(camera.cam_from_img(np.asarray(xy, np.float64).reshape(-1, 2)))  # type: ignore[union-attr]

    def distances_px(self, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        if not self.calibrated:
            return np.abs(sampson(self.matrix, xa, xb))
        # a model's images have cameras
        focal = 0.5 * (self.camera_a.mean_focal_length() + self.camera_b.mean_focal_length())  # type: ignore[union-attr]
        return focal * np.abs(sampson(self.matrix, self._normalised(xa, "a"), self._normalised(xb, "b")))

    def line(self, xy: tuple[float, float], side: str, width: int, height: int, samples: int = 64) -> list:
        """Polyline (COLMAP pixels, inside the other image) of the epipolar line/curve of a point in ``side``."""
        m = self.matrix if side == "a" else self.matrix.T
        if self.calibrated:
            l_ = m @ np.r_[self._normalised(xy, side)[0], 1.0]
            other = self.camera_b if side == "a" else self.camera_a
            # Sample the normalised line across the other camera's field of view, then distort.
            corners = np.asarray(
                # a model's images have cameras
                other.cam_from_img(np.array([[0, 0], [width, 0], [0, height], [width, height]], np.float64))  # type: ignore[union-attr]
            )
            lo, hi = corners.min(axis=0) * 1.5, corners.max(axis=0) * 1.5
            if abs(l_[1]) > abs(l_[0]):
                u = np.linspace(lo[0], hi[0], samples)
                pts = np.c_[u, -(l_[0] * u + l_[2]) / l_[1]]
            else:
                v = np.linspace(lo[1], hi[1], samples)
                pts = np.c_[-(l_[1] * v + l_[2]) / l_[0], v]
            # a model's images have cameras
            xy_img, ok = project(other, np.c_[pts, np.ones(len(pts))], margin_px=None)  # type: ignore[arg-type]
            ok &= (xy_img[:, 0] >= -width) & (xy_img[:, 0] <= 2 * width)
            ok &= (xy_img[:, 1] >= -height) & (xy_img[:, 1] <= 2 * height)
            return xy_img[ok].tolist()
        a, b, c = m @ np.array([xy[0], xy[1], 1.0])
        if abs(b) > abs(a):
            return [[0.0, -c / b], [float(width), -(a * width + c) / b]]
        return [[-c / a, 0.0], [-(b * height + c) / a, float(height)]]


def fit_model(
    xa: np.ndarray,
    xb: np.ndarray,
    threshold_px: float,
    camera_a: pycolmap.Camera | None = None,
    camera_b: pycolmap.Camera | None = None,
) -> tuple[EpipolarModel, np.ndarray] | None:
    """The model of the pairs so far (None below eight pairs) and the per-pair Sampson distance (px)."""
    xa, xb = np.asarray(xa, np.float64).reshape(-1, 2), np.asarray(xb, np.float64).reshape(-1, 2)
    if len(xa) < MIN_PAIRS:
        return None
    if camera_a is None:
        matrix, _ = robust_eight_point(xa, xb, threshold_px)
        model = EpipolarModel(matrix)
    else:
        # Calibrated: COLMAP's 5-point LO-RANSAC on the undistorted rays. (A linear 8-point E projected
        # onto the essential manifold is 30-140 px off for eight half-pixel-accurate clicks.)
        options = pycolmap.RANSACOptions()
        options.max_error = threshold_px
        options.random_seed = 0
        # a model's images have cameras
        found = pycolmap.estimate_essential_matrix(xa, xb, camera_a, camera_b, options)  # type: ignore[arg-type]
        if found is None:
            return None
        model = EpipolarModel(np.asarray(found["E"]), camera_a, camera_b)
    return model, model.distances_px(xa, xb)
