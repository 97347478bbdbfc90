"""The floor the epipolar bands' analysis points lie on when the world stage fitted none (``--world mapping``, or
no floor found): through scale.yaml's known lengths (bars on the floor), else the sparse points' dominant
horizontal plane. The world stage's own floor (``floor.estimate_floor``) is the one used when it found it."""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.core.geometry import Plane
from rigsfm.run.world.floor_model import floor_markers


def world_up(reconstruction: pycolmap.Reconstruction) -> np.ndarray:
    """The world's "up" for cameras mounted upright (small roll): orthogonal to every camera's x axis
    (horizontal whatever the pitch), on the side opposite the cameras' y axes; minus the mean y axis when all
    x axes are parallel (one rig)."""
    rotations = [im.cam_from_world().rotation.matrix() for im in reconstruction.images.values() if im.has_pose]
    down = np.mean([r[1] for r in rotations], axis=0)
    x_axes = np.array([r[0] for r in rotations])
    _, singular, vt = np.linalg.svd(x_axes)
    if len(singular) < 2 or singular[1] < 0.05 * singular[0]:
        return -down / np.linalg.norm(down)
    up = vt[-1]
    return up if up @ down < 0 else -up


def ground_plane(reconstruction: pycolmap.Reconstruction, min_points: int = 30, max_tilt_deg: float = 15.0,
                 iterations: int = 1000) -> Plane | None:
    """The floor from the sparse points: the plane holding the most points (RANSAC, threshold 0.3 % of the
    median camera-to-point distance) whose normal is within ``max_tilt_deg`` of :func:`world_up` and below every
    camera by more than 10 thresholds; None if no such plane holds ``min_points`` points."""
    rng = np.random.default_rng(0)
    xyz = np.array([p.xyz for p in reconstruction.points3D.values()]).reshape(-1, 3)
    centres = np.array([im.projection_center() for im in reconstruction.images.values() if im.has_pose])
    if len(xyz) < max(min_points, 3) or len(centres) < 1:
        return None
    up = world_up(reconstruction)
    min_cos = np.cos(np.radians(max_tilt_deg))
    threshold = 0.003 * float(np.median(np.linalg.norm(xyz - centres[0], axis=1)))
    best, best_count = None, 0
    samples = rng.choice(len(xyz), (iterations, 3))
    for a, b, c in xyz[samples]:
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) < 1e-12:
            continue
        normal /= np.linalg.norm(normal)
        if normal @ up < 0:
            normal = -normal
        offset = -float(normal @ a)
        if normal @ up < min_cos or np.any(centres @ normal + offset < 10 * threshold):
            continue
        count = int(np.sum(np.abs(xyz @ normal + offset) < threshold))
        if count > best_count:
            best, best_count = (normal, offset), count
    if best is None or best_count < min_points:
        return None
    inliers = xyz[np.abs(xyz @ best[0] + best[1]) < threshold]
    centroid = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centroid)[2][-1]
    normal = normal if normal @ best[0] > 0 else -normal
    return Plane(normal, -float(normal @ centroid), len(inliers))


def floor_from_known_lengths(reconstruction: pycolmap.Reconstruction, scale_spec) -> Plane | None:
    """The floor through the triangulated ends of scale.yaml's known lengths (bars lying on the floor), normal
    :func:`world_up`; None without a usable known length."""
    ends = floor_markers(reconstruction, scale_spec)
    if not len(ends):
        return None
    up = world_up(reconstruction)
    return Plane(up, -float(up @ ends.mean(axis=0)), len(ends))


def find_floor(reconstruction: pycolmap.Reconstruction, scale_spec=None) -> tuple[Plane | None, str]:
    """The floor through the known lengths, else from the sparse points when a tenth of them lie on it;
    ``(None, "none")`` without either. The second value says which (``known_lengths``, ``points``)."""
    plane = floor_from_known_lengths(reconstruction, scale_spec)
    if plane is not None:
        return plane, "known_lengths"
    plane = ground_plane(reconstruction, min_points=max(30, reconstruction.num_points3D() // 10))
    return (plane, "points") if plane is not None else (None, "none")
