"""Where a clicked point can be in the other narrow views, and where two or more clicks put it in the world.

Pixels are COLMAP's raw pixels of the narrow images (the lens model included); the world is the run's floor frame
(metres, z = 0 on the floor, z up).

- :func:`band_in_view`: the epipolar curve of a click between two heights: the ray from camera i through the click,
  its points at heights h in [h0, h1], projected into camera j with the one projection helper (points behind j or
  folded back by the lens model dropped), widened by the pair's calibrated 95 % band (``epipolar_band_95_px``).
- :func:`triangulate`: linear (DLT on the undistorted rays), then Gauss-Newton on the pixel residuals; its
  covariance propagates each click's noise and each camera's pose uncertainty (summary.json's 1-sigma centre and
  rotation, isotropic, the cameras taken as independent: the run keeps no joint covariance) to first order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.geometry import project_world, skew

CHI2_2D_95 = 5.991464547107979  # the 95 % quantile of chi-square with 2 degrees of freedom
SAMPLES = 160  # points of one band's centre curve


@dataclass(frozen=True)
class View:
    """One narrow image of the shown frame, with what its geometry needs."""

    name: str
    camera: pycolmap.Camera
    cam_from_world: pycolmap.Rigid3d
    centre_sigma_m: float = 0.0  # 1 sigma, RMS length of the 3D error
    rotation_sigma_rad: float = 0.0

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(self.cam_from_world.inverse().translation, np.float64)

    def ray(self, xy) -> np.ndarray:
        """Unit direction (world) of the ray through a raw pixel."""
        normalised = np.asarray(self.camera.cam_from_img(np.asarray(xy, np.float64).reshape(1, 2)))[0]
        direction = self.cam_from_world.rotation.inverse() * np.array([normalised[0], normalised[1], 1.0])
        return np.asarray(direction) / np.linalg.norm(direction)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return project_world(self.camera, self.cam_from_world, points, margin_px=None)


def ray_at_heights(view: View, xy, heights: np.ndarray) -> np.ndarray:
    """World points of the ray through ``xy`` at each height (NaN where the ray meets that height behind the camera
    or never)."""
    centre, direction = view.centre, view.ray(xy)
    heights = np.asarray(heights, np.float64)
    points = np.full((len(heights), 3), np.nan)
    if abs(direction[2]) < 1e-12:
        return points
    depth = (heights - centre[2]) / direction[2]
    ahead = depth > 0
    points[ahead] = centre + depth[ahead, None] * direction
    return points


@dataclass(frozen=True)
class Band:
    """A click's band in another view: the centre curve between the two heights, the half-width, the ticks."""

    view: int
    polyline: np.ndarray  # N x 2 raw pixels, from the lower height to the upper one
    band_px: float | None
    ticks: list[tuple[float, list[float]]]  # (height, pixel) of each tick height the curve reaches

    def distance(self, xy) -> float | None:
        """Distance (px) of a pixel from the centre curve (None when the curve is empty)."""
        return distance_to_polyline(self.polyline, xy)

    def to_dict(self) -> dict:
        return {"view": self.view, "polyline": np.round(self.polyline, 3).tolist(), "band_px": self.band_px,
                "ticks": [{"height": h, "xy": xy} for h, xy in self.ticks]}


def distance_to_polyline(polyline: np.ndarray, xy) -> float | None:
    p = np.asarray(polyline, np.float64).reshape(-1, 2)
    xy = np.asarray(xy, np.float64)
    if len(p) == 0:
        return None
    if len(p) == 1:
        return float(np.linalg.norm(p[0] - xy))
    a, b = p[:-1], p[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - xy, axis=1)))


def _longest_run(valid: np.ndarray) -> slice:
    best, start = slice(0, 0), None
    for k, ok in enumerate(np.append(valid, False)):
        if ok and start is None:
            start = k
        elif not ok and start is not None:
            if k - start > best.stop - best.start:
                best = slice(start, k)
            start = None
    return best


def band_in_view(view_i: View, xy, view_j: View, index_j: int, band_px: float | None, heights: tuple[float, float],
                 ticks: tuple[float, ...]) -> Band:
    """The band in ``view_j`` of a click ``xy`` in ``view_i`` (module docstring)."""
    h0, h1 = heights
    samples = np.linspace(h0, h1, SAMPLES)
    xy_j, seen = view_j.project(ray_at_heights(view_i, xy, samples))
    run = _longest_run(seen)  # a curve the lens model folds is cut, not joined across the fold
    tick_points = []
    for height in ticks:
        if h0 <= height <= h1:
            pixel, ok = view_j.project(ray_at_heights(view_i, xy, np.array([height])))
            if ok[0]:
                tick_points.append((float(height), [round(float(v), 3) for v in pixel[0]]))
    return Band(index_j, xy_j[run], band_px, tick_points)


def floor_trace(view: View, xy, heights: tuple[float, float], ticks: tuple[float, ...]) -> dict:
    """The ray's trace on the floor map between the two heights (world x, y) and its tick points."""
    ends = ray_at_heights(view, xy, np.array(heights, np.float64))
    marks = ray_at_heights(view, xy, np.array([t for t in ticks if heights[0] <= t <= heights[1]], np.float64))
    ok = np.all(np.isfinite(ends), axis=1)
    return {"segment": np.round(ends[ok, :2], 4).tolist(),
            "ticks": [{"height": float(p[2]), "xy": np.round(p[:2], 4).tolist()} for p in marks
                      if np.all(np.isfinite(p))],
            "camera": np.round(view.centre[:2], 4).tolist()}


@dataclass(frozen=True)
class Triangulation:
    xyz: np.ndarray
    covariance: np.ndarray  # 3 x 3, m^2
    residuals_px: np.ndarray  # per click, reprojection error of the refined point

    @property
    def height_sigma_m(self) -> float:
        return float(np.sqrt(max(self.covariance[2, 2], 0.0)))

    def floor_ellipse_95(self) -> dict:
        """Semi-axes (m) and the angle (deg, from world x) of the floor position's 95 % ellipse."""
        values, vectors = np.linalg.eigh(self.covariance[:2, :2])
        values = np.clip(values, 0.0, None)
        major = vectors[:, 1]
        return {"semi_axes_m": [float(np.sqrt(CHI2_2D_95 * values[1])), float(np.sqrt(CHI2_2D_95 * values[0]))],
                "angle_deg": float(np.degrees(np.arctan2(major[1], major[0])))}


STEP_M = 1e-5  # central differences of the projection (pycolmap's lens models have no Jacobian in Python)


def _projection_and_jacobian(view: View, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixel of a world point and its 2 x 3 Jacobian (central differences, one projection call)."""
    offsets = np.vstack([np.zeros(3), STEP_M * np.eye(3), -STEP_M * np.eye(3)])
    xy, _ = view.project(point + offsets)
    return xy[0], ((xy[1:4] - xy[4:7]) / (2 * STEP_M)).T


def _moved(view: View, d_centre: np.ndarray, d_rotation: np.ndarray) -> View:
    """The view with its centre moved and its orientation turned (world frame)."""
    world_from_cam = view.cam_from_world.inverse()
    rotation = pycolmap.Rotation3d(d_rotation) * world_from_cam.rotation if np.any(d_rotation) \
        else world_from_cam.rotation
    moved = pycolmap.Rigid3d(rotation, np.asarray(world_from_cam.translation) + d_centre).inverse()
    return View(view.name, view.camera, moved)


def triangulate(views: list[View], pixels: list, click_sigma_px: float) -> Triangulation | None:
    """The point two or more clicks (raw pixels, one per view) meet at, with its covariance; None when the rays
    do not meet in front of every camera."""
    pixels = [np.asarray(p, np.float64) for p in pixels]
    rows = []
    for view, xy in zip(views, pixels):
        x, y = np.asarray(view.camera.cam_from_img(xy.reshape(1, 2)))[0]
        m = view.cam_from_world.matrix()
        rows += [x * m[2] - m[0], y * m[2] - m[1]]
    _, _, vt = np.linalg.svd(np.asarray(rows))
    h = vt[-1]
    if abs(h[3]) < 1e-12:
        return None
    point = h[:3] / h[3]

    def linearised(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        found = [_projection_and_jacobian(v, p) for v in views]
        return (np.concatenate([xy - click for (xy, _), click in zip(found, pixels)]),
                np.vstack([jac for _, jac in found]))

    for _ in range(10):  # Gauss-Newton: three unknowns, a few iterations
        r, jac = linearised(point)
        if not np.all(np.isfinite(r)) or not np.all(np.isfinite(jac)):
            return None
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        point = point + step
        if np.linalg.norm(step) < 1e-9:
            break
    r, jac = linearised(point)
    if not np.all(np.isfinite(r)) or not np.all(np.isfinite(jac)):
        return None
    information = np.zeros((3, 3))
    for k, view in enumerate(views):
        j_point = jac[2 * k:2 * k + 2]
        # Moving the camera's centre by dc moves the point by -dc in its frame; turning the camera by w about its
        # centre (world frame) turns the point by -w: X' = C + Exp(-w) (X - C), dX'/dw = [X - C]x.
        j_rotation = j_point @ skew(point - view.centre)
        noise = (click_sigma_px ** 2 * np.eye(2) + view.centre_sigma_m ** 2 / 3 * j_point @ j_point.T
                 + view.rotation_sigma_rad ** 2 / 3 * j_rotation @ j_rotation.T)
        information += j_point.T @ np.linalg.solve(noise, j_point)
    try:
        covariance = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return None
    return Triangulation(point, covariance, np.linalg.norm(r.reshape(-1, 2), axis=1))
