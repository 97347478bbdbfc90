"""The floor fit's options and results, and the geometry it starts from: the cameras' up prior, the rig
positions, the known-length markers (``rigsfm.run.world.floor`` describes the method)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from rigsfm.core.names import name_of
from rigsfm.run.adjustment.scale import triangulate_observed_point
from rigsfm.run.inputs.scale_file import ScaleSpec


@dataclass(frozen=True)
class FloorOptions:
    max_tilt_deg: float = 25.0  # floor normal vs the up prior (x-axis prior); doubled for the -y fallback
    threshold: float | None = None  # RANSAC inlier distance (model units); None: 1 % of the camera height scale
    ransac_iterations: int = 3000  # most triples drawn at a time, until enough for 99.9 % confidence (_ransac)
    min_points: int = 30  # fewest inliers (and candidates) for a floor
    min_inlier_fraction: float = 0.05  # of the candidates below the cameras
    min_cells: int = 16  # inliers must occupy this many cells of side camera height / 2 (area >= 4 h^2)
    max_below_fraction: float = 0.5  # points well below a plane, per inlier, above which it is not the floor
    min_track_length: int = 2
    max_reprojection_error: float = 4.0  # px; points with a larger mean error are not candidates
    seed: int = 0
    # When the sparse points (and markers) alone are enough, i.e. floor matching is skipped:
    enough_points: int = 100
    enough_normal_sigma_deg: float = 0.02
    enough_height_sigma: float = 0.002  # x the median camera height (7 mm at 3.5 m)


@dataclass(frozen=True)
class NoFloor:
    """No floor could be found; ``reason`` says why (for a warning). Falsy, so ``if not fit:`` works."""

    reason: str

    def __bool__(self) -> bool:
        return False


@dataclass(frozen=True)
class FloorFit:
    """The floor plane ``normal @ x + offset = 0`` in the model frame (normal up, unit) and the floor frame."""

    normal: np.ndarray
    offset: float
    rms: float  # RMS point-to-plane residual of the inliers (model units)
    robust_sigma: float  # 1.4826 MAD of the inliers' residuals
    threshold: float  # final inlier distance
    num_points: int  # floor points used in the final fit (all sources)
    num_candidates: int  # points below all cameras (all sources)
    points_by_source: dict[str, int]  # floor points per source: "sparse", "matched", "markers"
    up_prior: np.ndarray
    up_prior_source: str  # "camera x axes" or "camera -y axes"
    prior_angle_deg: float  # angle between the fitted normal and the up prior
    floor_from_model: pycolmap.Rigid3d
    origin_rig: str  # the rig the x axis points towards
    camera_heights: dict[str, float]  # image name -> camera centre height above the floor
    marker_residuals: list[float] = field(default_factory=list)  # signed height of each marker point
    below_fraction: float = 0.0  # candidates below the plane by > max(3 thresholds, 5 % camera height), per inlier
    inlier_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # point3D ids
    warnings: tuple[str, ...] = ()
    # Standard errors of the normal's tilt (largest axis) and of the cameras' heights (the largest), the points of
    # one image pair sharing its pose error (floor_fit.grouped_plane_precision)
    normal_sigma_deg: float = float("inf")
    height_sigma: float = float("inf")
    # The same with every point an independent draw: the points' scatter alone, a lower bound (floor_fit.plane_precision);
    # what decides whether more points are needed (floor.sparse_floor_shortfall)
    scatter_normal_sigma_deg: float = float("inf")
    scatter_height_sigma: float = float("inf")
    group_sigma: float = float("inf")  # spread of the image pairs' shared offsets from the plane (model units)
    num_groups: int = 0  # image pairs (groups of points sharing a pose error) among the inliers
    effective_groups: float = 0.0  # (sum n)^2 / sum n^2 of their sizes: how many equal pairs they weigh as
    sigma_basis: str = ""  # what normal_sigma_deg and height_sigma rest on (weakly determined, a lower bound)
    camera_height_sigmas: dict[str, float] = field(default_factory=dict)  # image name -> the floor's part of its sigma
    # The normal's sigma from the pairs' residuals alone (grouped_plane_precision), and from the poses' covariance
    # carried through the floor points (floor_poses.pose_floor_covariance; NaN where not propagated)
    grouped_normal_sigma_deg: float = float("inf")
    pose_normal_sigma_deg: float = float("nan")
    # image name -> its height's 1 sigma from the poses' covariance, the camera and the floor moved together by the same
    # poses (floor_poses.pose_floor_covariance; empty where not propagated)
    pose_camera_height_sigmas: dict[str, float] = field(default_factory=dict)

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed height above the floor of model-frame points (Nx3)."""
        return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ self.normal + self.offset

    def to_dict(self) -> dict:
        heights = np.array(list(self.camera_heights.values()))
        return {
            "rms": self.rms,
            "robust_sigma": self.robust_sigma,
            "threshold": self.threshold,
            "num_points": self.num_points,
            "num_candidates": self.num_candidates,
            "points_by_source": self.points_by_source,
            "normal_in_model": self.normal.tolist(),
            "up_prior_source": self.up_prior_source,
            "prior_angle_deg": self.prior_angle_deg,
            "origin_rig": self.origin_rig,
            "floor_from_model": {
                "rotation": self.floor_from_model.rotation.matrix().tolist(),
                "translation": self.floor_from_model.translation.tolist(),
            },
            "camera_height": {"min": float(heights.min()), "max": float(heights.max())} if heights.size else None,
            "normal_sigma_deg": self.normal_sigma_deg,
            "camera_height_sigma": self.height_sigma,
            "scatter_normal_sigma_deg": self.scatter_normal_sigma_deg,
            "scatter_camera_height_sigma": self.scatter_height_sigma,
            "group_sigma": self.group_sigma if np.isfinite(self.group_sigma) else None,  # None: under 4 pairs
            "num_groups": self.num_groups,
            "effective_groups": self.effective_groups,
            "sigma_basis": self.sigma_basis,
            "grouped_normal_sigma_deg": self.grouped_normal_sigma_deg,
            "pose_normal_sigma_deg": None if np.isnan(self.pose_normal_sigma_deg) else self.pose_normal_sigma_deg,
            "marker_residuals": self.marker_residuals,
            "warnings": list(self.warnings),
        }


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through Nx3 points: unit normal n and offset d with n @ x + d = 0."""
    p = np.asarray(points, dtype=np.float64)
    centroid = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centroid, full_matrices=False)
    normal = vt[-1]
    return normal, float(-normal @ centroid)


def posed_images(reconstruction: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted((im for im in reconstruction.images.values() if im.has_pose), key=lambda im: im.name)


def up_prior(reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, str]:
    """The cameras' common up direction (unit, model frame) and how it was found (see the module docstring)."""
    images = posed_images(reconstruction)
    if not images:
        raise ValueError("no registered image")
    world_from_cam = np.array([im.cam_from_world().rotation.matrix().T for im in images])
    x_axes, minus_y = world_from_cam[:, :, 0], -world_from_cam[:, :, 1]
    mean_minus_y = minus_y.mean(axis=0)
    values, vectors = np.linalg.eigh(x_axes.T @ x_axes / len(images))
    # Eigenvalues sum to 1; x axes spread over >= 2 directions make the second-smallest one large.
    if values[1] > 0.05:
        up = vectors[:, 0]
        source = "camera x axes"
    else:
        mean_x = x_axes.mean(axis=0)
        mean_x /= np.linalg.norm(mean_x)
        up = mean_minus_y - (mean_minus_y @ mean_x) * mean_x
        source = "camera -y axes"
    up = up / np.linalg.norm(up)
    if up @ mean_minus_y < 0:
        up = -up
    return up, source


def rig_positions(reconstruction: pycolmap.Reconstruction) -> dict[int, tuple[str, np.ndarray]]:
    """rig id -> (rig name, mean reference-camera centre over its registered frames)."""
    names: dict = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            names.setdefault(reconstruction.frame(image.frame_id).rig_id, name_of(image).rig)
    centres: dict[int, list[np.ndarray]] = {}
    for frame in reconstruction.frames.values():
        if frame.has_pose:
            centres.setdefault(frame.rig_id, []).append(np.asarray(frame.rig_from_world.inverse().translation))
    return {rig_id: (names.get(rig_id, f"rig{rig_id}"), np.mean(c, axis=0)) for rig_id, c in sorted(centres.items())}


def floor_markers(reconstruction: pycolmap.Reconstruction, spec: ScaleSpec | None) -> np.ndarray:
    """The end points of every known length of ``spec`` triangulated in the model (Mx3; those with fewer than
    two registered images are skipped). Known lengths are marked on the floor (README), so they are floor."""
    points = []
    for item in spec.known_lengths if spec is not None else ():
        for end in ("a", "b"):
            point = triangulate_observed_point(
                reconstruction, [(o.image, np.asarray(getattr(o, end), dtype=np.float64)) for o in item.observations]
            )
            if point is not None:
                points.append(point)
    return np.asarray(points, dtype=np.float64).reshape(-1, 3)
