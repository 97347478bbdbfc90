"""Simulated user clicks: correspondences between two wide images of a rendered arena, from ground truth.

A careful user picking points for ``--manual-matches`` spreads them over the part of the scene both views
show, on distinctive spots of every kind of structure there (stands, pillars, boxes, textured ground). The
simulation does the same: candidate points on each surface visible and unoccluded in both images, each
surface's share picked by farthest-point sampling in the first image, then pixel noise and gross outliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.geometry import project_world
from rigsfm.run.matching.manual_matches import Correspondence
from rigsfm.synth.render import visible
from rigsfm.synth.scene import Arena, Box, Pillar

SURFACES = ("wall", "objects", "ground")
MARGIN_PX = 20.0
LIFT = 1e-3  # candidates sit 1 mm in front of their surface, so the occlusion test sees them


@dataclass(frozen=True)
class Clicks:
    rows: list[Correspondence]
    outliers: np.ndarray  # True where the partner in image B is a random, wrong point
    points: np.ndarray  # the true 3D points (N x 3)


def _pillar_points(pillar: Pillar, rng: np.random.Generator, m: int) -> np.ndarray:
    phi, z = rng.uniform(0, 2 * np.pi, m), rng.uniform(0.1, pillar.height - 0.1, m)
    r = pillar.radius + LIFT
    return np.column_stack([pillar.x + r * np.cos(phi), pillar.y + r * np.sin(phi), z])


def _box_points(box: Box, rng: np.random.Generator, m: int) -> np.ndarray:
    """Points on the four sides and the top of a box (its corners included)."""
    half = np.asarray(box.half_size)
    local = rng.uniform(-1, 1, (m, 3)) * half
    face = rng.integers(0, 5, m)  # 0-3: the sides (+-x, +-y), 4: the top
    axis, sign = np.where(face < 4, face // 2, 2), np.where((face % 2 == 0) | (face == 4), 1.0, -1.0)
    local[np.arange(m), axis] = sign * (half[axis] + LIFT)
    corners = np.array([[sx, sy, 1.0] for sx in (-1, 1) for sy in (-1, 1)]) * (half + LIFT)
    local = np.vstack([corners, local])
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    world = np.column_stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]])
    return world + np.array([box.x, box.y, half[2]])


def candidate_points(arena: Arena, rng: np.random.Generator, m: int = 6000) -> dict[str, np.ndarray]:
    """Random points on the textured ground ring, the wall (stands) and the pillars and boxes."""
    opt = arena.options
    r = np.sqrt(rng.uniform((opt.centre_radius + 1) ** 2, (opt.wall_radius - 0.5) ** 2, m))
    phi, theta = rng.uniform(0, 2 * np.pi, m), rng.uniform(0, 2 * np.pi, m)
    wall_r = opt.wall_radius - LIFT
    objects = [_pillar_points(p, rng, m // 10) for p in arena.pillars]
    objects += [_box_points(b, rng, m // 10) for b in arena.boxes]
    return {
        "ground": np.column_stack([r * np.cos(phi), r * np.sin(phi), np.full(m, LIFT)]),
        "wall": np.column_stack(
            [wall_r * np.cos(theta), wall_r * np.sin(theta), rng.uniform(0.2, opt.wall_height - 0.2, m)]
        ),
        "objects": np.vstack(objects) if objects else np.zeros((0, 3)),
    }


def farthest_points(xy: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``count`` points of ``xy`` picked one by one, each as far as possible from the others."""
    chosen = [int(rng.integers(len(xy)))]
    distance = np.linalg.norm(xy - xy[chosen[0]], axis=1)
    while len(chosen) < min(count, len(xy)):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(xy - xy[chosen[-1]], axis=1))
    return np.array(chosen)


def simulate_clicks(
    arena: Arena,
    truth: pycolmap.Reconstruction,
    image_a: str,
    image_b: str,
    n: int = 34,
    noise_px: float = 1.0,
    outlier_fraction: float = 0.2,
    seed: int = 0,
    surfaces: tuple[str, ...] = SURFACES,
) -> Clicks:
    """``n`` correspondences ``image_a`` <-> ``image_b``, shared equally by the ``surfaces`` both views show.

    Noise is Gaussian, ``noise_px`` per coordinate; outliers get a uniformly random point in image B.
    Raises ValueError when the two views share no point of the requested surfaces.
    """
    views = [(truth.cameras[im.camera_id], im.cam_from_world()) for im in map(truth.find_image_with_name,
                                                                             (image_a, image_b))]
    rng = np.random.default_rng(seed)
    candidates = candidate_points(arena, rng)
    pools = []
    for surface in surfaces:
        pts = candidates[surface]
        pts = pts[np.logical_and.reduce([visible(arena, cam, pose, pts, MARGIN_PX) for cam, pose in views])]
        if len(pts):
            pools.append(pts)
    if sum(map(len, pools)) < n:
        raise ValueError(f"{image_a} and {image_b} share fewer than {n} points on {', '.join(surfaces)}")
    chosen: list[np.ndarray] = []
    for k, pts in enumerate(pools):
        count = n // len(pools) if k < len(pools) - 1 else n - sum(map(len, chosen))
        chosen.append(pts[farthest_points(project_world(*views[0], pts, margin_px=None)[0], count, rng)])
    points = np.vstack(chosen)
    xy = [project_world(camera, pose, points, margin_px=None)[0] + rng.normal(0, noise_px, (len(points), 2))
          for camera, pose in views]
    outliers = np.zeros(len(points), bool)
    outliers[rng.choice(len(points), round(outlier_fraction * len(points)), replace=False)] = True
    cam_b = views[1][0]
    xy[1][outliers] = rng.uniform([MARGIN_PX] * 2, [cam_b.width - MARGIN_PX, cam_b.height - MARGIN_PX],
                                  (int(outliers.sum()), 2))
    # 2D points
    rows = [Correspondence(image_a, tuple(map(float, p)), image_b, tuple(map(float, q)), i + 2)  # type: ignore[arg-type]
            for i, (p, q) in enumerate(zip(*xy))]
    return Clicks(rows, outliers, points)
