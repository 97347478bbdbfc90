"""Geometry shared by every verb: the one projection helper, the one Sampson error, epipolar lines and
two-view measures on calibrated cameras, the one ``skew`` and the one ``Plane``.

Pixels are COLMAP's (centre of the first pixel at (0.5, 0.5)) throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

Config = pycolmap.TwoViewGeometryConfiguration
PLANAR = (Config.PLANAR, Config.PANORAMIC, Config.PLANAR_OR_PANORAMIC)  # a homography explains the matches
POSED = (Config.CALIBRATED, Config.UNCALIBRATED, *PLANAR)  # configurations that carry a relative pose

ROUND_TRIP_TOLERANCE = 1e-6  # normalised image units (~0.004 px at f = 3600)


def project(camera: pycolmap.Camera, points_in_cam: np.ndarray, *, margin_px: float | None = 0.0,
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of points given in camera coordinates (N x 3), and which of them are seen.

    A point is seen when it lies in front of the camera, within the range where the lens model is
    monotonic (``Camera.img_from_cam`` folds points far outside a view back into the image: their pixel does
    not map back onto their own ray through ``cam_from_img``), and, unless ``margin_px`` is None, inside the
    image at least ``margin_px`` from its border. Pixels of points not seen are NaN.
    """
    points = np.asarray(points_in_cam, dtype=np.float64).reshape(-1, 3)
    seen = points[:, 2] > 1e-12
    xy = np.full((len(points), 2), np.nan)
    if seen.any():
        xy[seen] = np.asarray(camera.img_from_cam(points[seen], check_cheirality=False), dtype=np.float64)
    with np.errstate(invalid="ignore"):
        seen &= np.all(np.isfinite(xy), axis=1)
        if margin_px is not None:
            seen &= (xy[:, 0] >= margin_px) & (xy[:, 0] <= camera.width - margin_px)
            seen &= (xy[:, 1] >= margin_px) & (xy[:, 1] <= camera.height - margin_px)
    if seen.any():  # the round trip (an iterative undistortion) only where the pixel would count
        with np.errstate(invalid="ignore", divide="ignore"):
            back = np.asarray(camera.cam_from_img(xy[seen]), dtype=np.float64)
            normalised = points[seen, :2] / points[seen, 2:]
            scale = np.maximum(1.0, np.abs(normalised))
            folds = ~np.all(np.abs(back - normalised) <= ROUND_TRIP_TOLERANCE * scale, axis=1)
        seen[np.flatnonzero(seen)[folds]] = False
    xy[~seen] = np.nan
    return xy, seen


def project_world(camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d, points: np.ndarray, *,
                  margin_px: float | None = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project` for world points (N x 3) seen from ``cam_from_world``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    m = cam_from_world.matrix()
    return project(camera, points @ m[:, :3].T + m[:, 3], margin_px=margin_px)


def sampson(matrix: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed Sampson distance of each correspondence ``x2^T M x1 = 0`` (M an essential or fundamental matrix),
    in the units of the coordinates (N x 2 each)."""
    h1 = np.column_stack([np.asarray(x1, np.float64), np.ones(len(x1))])
    h2 = np.column_stack([np.asarray(x2, np.float64), np.ones(len(x2))])
    mx1, mtx2 = h1 @ matrix.T, h2 @ matrix
    num = np.sum(h2 * mx1, axis=1)
    den = np.sqrt(mx1[:, 0] ** 2 + mx1[:, 1] ** 2 + mtx2[:, 0] ** 2 + mtx2[:, 1] ** 2)
    return num / np.maximum(den, 1e-300)


def sampson_error_px(
    essential: np.ndarray, cam1: pycolmap.Camera, cam2: pycolmap.Camera, xy1: np.ndarray, xy2: np.ndarray
) -> np.ndarray:
    """Sampson epipolar error of each correspondence of raw pixels (``x2^T E x1 = 0``), in pixels via the mean
    focal length of both cameras."""
    n1 = np.asarray(cam1.cam_from_img(np.asarray(xy1, np.float64)))
    n2 = np.asarray(cam2.cam_from_img(np.asarray(xy2, np.float64)))
    focal = 0.5 * (cam1.mean_focal_length() + cam2.mean_focal_length())
    return np.abs(sampson(essential, n1, n2)) * focal


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


def triangulate_views(cams_from_world: np.ndarray, views: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """World points (P x 3; NaN where none) of points seen n times each, all at once: COLMAP's linear triangulation
    (``pycolmap.triangulate_point``'s DLT null vector for two views, its rows in that order for n).
    ``cams_from_world``: the poses (F x 3 x 4); ``views``: which pose took each observation (P x n); ``rays``: the
    observations' normalised rays (P x n x 2)."""
    pose = np.asarray(cams_from_world)[np.asarray(views)]  # P x n x 3 x 4
    rows = np.stack([rays[..., :1] * pose[..., 2, :] - pose[..., 0, :],
                     rays[..., 1:] * pose[..., 2, :] - pose[..., 1, :]], axis=2).reshape(len(rays), -1, 4)
    points = np.full((len(rows), 3), np.nan)
    ok = np.isfinite(rows).all(axis=(1, 2))
    if ok.any():
        null = np.linalg.svd(rows[ok])[2][:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            points[ok] = null[:, :3] / null[:, 3:]
    return points


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix: ``skew(v) @ w == np.cross(v, w)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class Plane:
    normal: np.ndarray  # unit, pointing to the cameras' side
    offset: float  # normal . x + offset = 0
    inliers: int

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Ray parameter of each ray's intersection (inf when parallel or behind)."""
        denominator = directions @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -(origins @ self.normal + self.offset) / denominator
        return np.where((np.abs(denominator) > 1e-12) & (s > 0), s, np.inf)


def epipolar_lines(camera_i: pycolmap.Camera, camera_j: pycolmap.Camera, j_from_i: pycolmap.Rigid3d,
                   pixels_i: np.ndarray) -> np.ndarray:
    """Lines (a, b, c) in camera j's pinhole pixels for raw pixels of image i (distortion removed)."""
    rays = np.asarray(camera_i.cam_from_img(np.asarray(pixels_i, dtype=np.float64)))
    rays = np.column_stack([rays, np.ones(len(rays))])
    essential = np.asarray(pycolmap.essential_matrix_from_pose(j_from_i))
    k_j = np.asarray(camera_j.calibration_matrix())
    return (np.linalg.inv(k_j).T @ essential @ rays.T).T


def pixel_line_distances(lines: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Distance (pixels) of each pixel (N x 2) from its line (N x 3, a x + b y + c = 0), both in one image's
    undistorted pixels."""
    return np.abs(np.einsum("ij,ij->i", lines, np.c_[pixels, np.ones(len(pixels))])) / np.linalg.norm(
        lines[:, :2], axis=1)


def line_distances(camera_j: pycolmap.Camera, lines: np.ndarray, points_in_j: np.ndarray) -> np.ndarray:
    """Signed distance (pinhole pixels of j) of the projection of camera-j points from pixel lines."""
    k_j = np.asarray(camera_j.calibration_matrix())
    projected = points_in_j @ k_j.T
    projected = projected / projected[..., 2:3]
    return np.sum(lines * projected, axis=-1) / np.linalg.norm(lines[..., :2], axis=-1)


def correspondence_check(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, name_i: str,
                         name_j: str, world_points: np.ndarray) -> np.ndarray:
    """Distances (pinhole px of j) of true correspondences from their estimated epipolar lines.

    ``world_points`` (truth's frame) are projected with the true poses and cameras into both raw images; those
    seen by both give a true pixel pair, whose image-i pixel defines the estimated epipolar line in j (estimated
    cameras and pose) and whose image-j pixel (undistorted with the estimated camera j) is measured against it.
    """
    pixels = []
    for name in (name_i, name_j):
        image = truth.find_image_with_name(name)
        pixels.append(project_world(truth.cameras[image.camera_id], image.cam_from_world(),
                                    np.asarray(world_points, dtype=np.float64)))
    both = pixels[0][1] & pixels[1][1]
    if not both.any():
        return np.zeros(0)
    image_i, image_j = (estimate.find_image_with_name(n) for n in (name_i, name_j))
    camera_i, camera_j = estimate.cameras[image_i.camera_id], estimate.cameras[image_j.camera_id]
    j_from_i = image_j.cam_from_world() * image_i.cam_from_world().inverse()
    lines = epipolar_lines(camera_i, camera_j, j_from_i, pixels[0][0][both])
    rays_j = np.asarray(camera_j.cam_from_img(pixels[1][0][both]))
    return np.abs(line_distances(camera_j, lines, np.column_stack([rays_j, np.ones(len(rays_j))])))


def align_points(source: np.ndarray, target: np.ndarray, *, scaled: bool) -> pycolmap.Sim3d | None:
    """``target_from_source`` minimising |s R source + t - target| over N x 3 points (Umeyama; s = 1 unless
    ``scaled``: a wrong metric scale then stays an error); None with fewer than three points or all on one line,
    where a rotation about it is free."""
    source, target = np.asarray(source, dtype=float).reshape(-1, 3), np.asarray(target, dtype=float).reshape(-1, 3)
    if len(source) < 3:
        return None
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    u, d, vt = np.linalg.svd((target - mt).T @ (source - ms))
    if d[1] <= 1e-9 * max(d[0], 1e-300):
        return None
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / np.sum((source - ms) ** 2)) if scaled else 1.0
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), mt - scale * rotation @ ms)
