"""Metres on the ground, per camera: plane homographies, footprints, ground sampling distance, overlaps.

Everything here works in the reconstruction's world frame and assumes it is the **floor frame** (z = 0 on the
floor, z up, metres: :mod:`rigsfm.run.world.frame`). A "plane at height h" is ``z = h`` (e.g.
``h = 1.7`` for heads).

- ``ground_from_image(image, h)``: 3x3 homography from **undistorted COLMAP pixels** (the pinhole ``K`` of the
  camera, first pixel centre at (0.5, 0.5) -- the convention of ``F_ji`` in narrow_poses.json) to plane
  coordinates ``(x, y, 1)`` in metres. It is scaled so that ``w > 0`` exactly for pixels whose ray meets the
  plane in front of the camera (below the horizon); divide by ``w`` to get (x, y). Raw (distorted) pixels go
  through :func:`image_to_plane`, which undistorts with the camera model first.
- ``footprint(image, h)``: the part of the plane the image sees, as a counter-clockwise polygon in metres: the
  image border (pixel edges, ``[0, W] x [0, H]`` in COLMAP pixels) sampled densely, undistorted with the
  camera model, intersected with the plane; rays above the horizon, or meeting the plane farther than
  ``max_depth`` (camera z; default 20 camera heights, a 3 degree grazing angle) are clipped away at a straight
  line on the plane (``clipped`` is then True). A pinhole footprint below the horizon is convex; lens
  distortion bends its edges slightly (``convex`` says which).
- ``gsd_mm_per_px``: at the footprint centre (where the ray of the image centre ``(W/2, H/2)`` meets the
  plane), sqrt(|det J|) of the pixel -> plane Jacobian (mm per pixel, area-equivalent); ``gsd_mm_per_px_xy``
  the lengths along the image x and y axes (the along-view one is larger at grazing angles).
- Overlaps: exact pairwise polygon intersections (:func:`intersect_polygons`; Sutherland-Hodgman against a
  convex clip polygon, or against the convex pieces of a non-convex one: :func:`convex_pieces`), and a raster coverage count
  (:func:`coverage`) for "seen by at least k cameras".
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.names import ImageName
from rigsfm.core.polygons import (
    clip_half_plane,
    intersect_polygons,
    intersection_area,
    is_convex,
    polygon_area,
)

logger = logging.getLogger(__name__)


# --- homographies -----------------------------------------------------------------------------------------


def image_from_plane(image: pycolmap.Image, height: float = 0.0) -> np.ndarray:
    """3x3: plane point (x, y, 1) on z = ``height`` -> homogeneous undistorted COLMAP pixel, ``K [r1 r2 h r3 + t]``
    (third coordinate = depth in the camera)."""
    pose = image.cam_from_world()
    rotation, translation = pose.rotation.matrix(), np.asarray(pose.translation)
    # a model's images have their cameras
    k = np.asarray(image.camera.calibration_matrix(), dtype=np.float64)  # type: ignore[union-attr]
    return k @ np.column_stack([rotation[:, 0], rotation[:, 1], height * rotation[:, 2] + translation])


def ground_from_image(image: pycolmap.Image, height: float = 0.0) -> np.ndarray:
    """3x3: undistorted COLMAP pixel (u, v, 1) -> (x, y, w) on the plane z = ``height``; ``w > 0`` for pixels
    whose ray meets the plane in front of the camera (see the module docstring)."""
    forward = image_from_plane(image, height)
    if abs(np.linalg.det(forward)) < 1e-12 * np.linalg.norm(forward) ** 3:
        raise ValueError(f"{image.name}: the camera centre lies on the plane z = {height}")
    g = np.linalg.inv(forward)  # w = 1 / depth: positive in front
    scale = abs(g[2, 2]) if abs(g[2, 2]) > 1e-12 * np.linalg.norm(g) else np.linalg.norm(g)
    return g / scale


def undistort_pixels(camera: pycolmap.Camera, pixels: np.ndarray) -> np.ndarray:
    """Raw COLMAP pixels -> undistorted COLMAP pixels of the same camera's pinhole ``K`` (NaN where the model
    cannot be inverted)."""
    normalised = camera.cam_from_img(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    k = np.asarray(camera.calibration_matrix(), dtype=np.float64)
    return normalised @ k[:2, :2].T + k[:2, 2]  # type: ignore[operator]  # pixels in: rays out


def image_to_plane(image: pycolmap.Image, pixels: np.ndarray, height: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Raw (distorted) COLMAP pixels (Nx2) -> plane points (Nx2, metres) on z = ``height`` and a mask of the
    pixels whose ray meets the plane in front of the camera."""
    # a model's images have their cameras
    normalised = image.camera.cam_from_img(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))  # type: ignore[union-attr]
    # rays out
    rays = np.c_[normalised, np.ones(len(normalised))] @ image.cam_from_world().rotation.matrix()  # type: ignore[arg-type]
    centre = np.asarray(image.projection_center())
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (height - centre[2]) / rays[:, 2]
    valid = np.isfinite(t) & (t > 0)
    xy = centre[:2] + np.where(valid, t, np.nan)[:, None] * rays[:, :2]
    return xy, valid


# --- footprints -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Footprint:
    image: str
    height: float  # the plane z = height
    polygon: np.ndarray  # Kx2 metres on the plane, counter-clockwise
    area: float  # m^2
    centre: np.ndarray | None  # (x, y) where the image centre's ray meets the plane
    gsd_mm_per_px: float | None  # sqrt |det J| at the centre
    gsd_mm_per_px_xy: tuple[float, float] | None  # along image x, image y
    camera_height: float  # camera centre above the plane
    clipped: bool  # part of the image is above the horizon or beyond max_depth
    convex: bool

    def to_dict(self) -> dict:
        return {
            "image": self.image,
            "plane_height_m": self.height,
            "camera_height_m": self.camera_height,
            "polygon_m": self.polygon.tolist(),
            "area_m2": self.area,
            "centre_m": None if self.centre is None else self.centre.tolist(),
            "gsd_mm_per_px": self.gsd_mm_per_px,
            "gsd_mm_per_px_xy": None if self.gsd_mm_per_px_xy is None else list(self.gsd_mm_per_px_xy),
            "clipped": self.clipped,
            "convex": self.convex,
        }


def image_border(width: int, height: int, samples_per_side: int) -> np.ndarray:
    """Points along the image's outer edge (COLMAP pixels, pixel edges at 0 and W/H), clockwise on screen
    (x right, y down), corners included once."""
    t = np.linspace(0.0, 1.0, samples_per_side, endpoint=False)
    top = np.c_[t * width, np.zeros_like(t)]
    right = np.c_[np.full_like(t, width), t * height]
    bottom = np.c_[(1 - t) * width, np.full_like(t, height)]
    left = np.c_[np.zeros_like(t), (1 - t) * height]
    return np.vstack([top, right, bottom, left])


def footprint(image: pycolmap.Image, height: float = 0.0, *, samples_per_side: int = 64,
              max_depth: float | None = None) -> Footprint | None:
    """The image's footprint on the plane z = ``height`` (module docstring); None when the camera is not above
    the plane or sees none of it."""
    camera = image.camera
    centre3 = np.asarray(image.projection_center())
    above = float(centre3[2] - height)
    if above <= 0:
        logger.debug("%s is not above the plane z = %g", image.name, height)
        return None
    max_depth = 20.0 * above if max_depth is None else float(max_depth)
    # a model's images have their cameras
    border = image_border(camera.width, camera.height, samples_per_side)  # type: ignore[union-attr]
    normalised = camera.cam_from_img(border)  # type: ignore[union-attr]
    finite = np.isfinite(normalised).all(axis=1)
    if not finite.all():
        logger.warning("%s: %d border points cannot be undistorted and are skipped", image.name, int((~finite).sum()))
        normalised = normalised[finite]
    world_from_cam = image.cam_from_world().rotation.matrix().T
    r3 = world_from_cam[2]  # world z of a camera ray (x, y, 1) = r3 @ (x, y, 1)
    # Keep rays with depth <= max_depth at the plane: r3 . (x, y, 1) <= -above / max_depth (a line).
    normal, offset = -r3[:2], -r3[2] - above / max_depth
    clipped = bool(np.any(normalised @ normal + offset < 0))
    kept = clip_half_plane(normalised, normal, offset)
    if len(kept) < 3:
        return None
    rays = np.c_[kept, np.ones(len(kept))] @ world_from_cam.T
    t = -above / rays[:, 2]
    polygon = centre3[:2] + t[:, None] * rays[:, :2]
    if polygon_area(polygon) < 0:
        polygon = polygon[::-1]
    centre_xy, gsd, gsd_xy = None, None, None
    # a model's images have their cameras
    middle = np.array([[camera.width / 2.0, camera.height / 2.0]])  # type: ignore[union-attr]
    xy, valid = image_to_plane(image, middle, height)
    if valid[0]:
        depth = float((image.cam_from_world() * np.r_[xy[0], height])[2])
        if depth <= max_depth:
            centre_xy = xy[0]
            step = 0.5
            probes = middle + np.array([[step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]])
            p, ok = image_to_plane(image, probes, height)
            if ok.all():
                jac = np.column_stack([(p[0] - p[1]) / (2 * step), (p[2] - p[3]) / (2 * step)])
                gsd = 1000.0 * float(np.sqrt(abs(np.linalg.det(jac))))
                gsd_xy = (1000.0 * float(np.linalg.norm(jac[:, 0])), 1000.0 * float(np.linalg.norm(jac[:, 1])))
    return Footprint(image.name, float(height), polygon, polygon_area(polygon), centre_xy, gsd, gsd_xy, above,
                     clipped, is_convex(polygon, 1e-6))


def _sensor(name: str) -> str | None:
    try:
        return str(ImageName.parse(name).sensor)
    except ValueError:
        return None


def footprints(reconstruction: pycolmap.Reconstruction, sensor: str = "narrow", height: float = 0.0,
               **kwargs) -> dict[str, Footprint]:
    """Footprints of every registered ``<rig>/<sensor>/...`` image (those that see the plane)."""
    result = {}
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if image.has_pose and _sensor(image.name) == sensor:
            fp = footprint(image, height, **kwargs)
            if fp is not None:
                result[image.name] = fp
    return result


@dataclass(frozen=True)
class Overlap:
    a: str
    b: str
    area: float  # m^2
    pieces: list[np.ndarray]  # disjoint counter-clockwise polygons


def pairwise_overlaps(prints: dict[str, Footprint], min_area: float = 0.0, *, pieces: bool = True) -> list[Overlap]:
    """Exact intersections of every pair of footprints with more than ``min_area`` m^2 in common; with
    ``pieces=False`` only their areas (:func:`intersection_area`, much faster on distorted footprints)."""
    result = []
    for (name_a, a), (name_b, b) in itertools.combinations(sorted(prints.items()), 2):
        lo = np.maximum(a.polygon.min(axis=0), b.polygon.min(axis=0))
        hi = np.minimum(a.polygon.max(axis=0), b.polygon.max(axis=0))
        if np.any(lo >= hi):
            continue
        if pieces:
            parts = intersect_polygons(a.polygon, b.polygon)
            area = float(sum(polygon_area(p) for p in parts))
        else:
            parts, area = [], intersection_area(a.polygon, b.polygon)
        if area > min_area:
            result.append(Overlap(name_a, name_b, area, parts))
    return result


@dataclass(frozen=True)
class Coverage:
    """How many footprints cover each cell of a grid on the plane (cell centres at origin + (i + 0.5) cell)."""

    counts: np.ndarray  # rows = y, cols = x
    origin: np.ndarray  # (x, y) of the grid's lower-left corner
    cell: float

    def area_at_least(self, k: int) -> float:
        return float(np.count_nonzero(self.counts >= k)) * self.cell**2

    def outlines(self, k: int) -> list[np.ndarray]:
        """Outer outlines (metres, counter-clockwise) of the regions seen by at least ``k`` footprints."""
        mask = (self.counts >= k).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        result = []
        for contour in contours:
            poly = self.origin + (contour.reshape(-1, 2).astype(np.float64) + 0.5) * self.cell
            result.append(poly if polygon_area(poly) >= 0 else poly[::-1])
        return result


MAX_COVERAGE_CELLS = 2e7  # 40 MB of counts: 5 cm cells over 220 x 220 m


def coverage(prints: Mapping[str, Footprint | np.ndarray], cell: float = 0.05) -> Coverage:
    """Rasterise every footprint (or polygon; ``cv2.fillPoly``, 1/256-cell vertex precision) and count per
    cell (``cell`` metres, larger where the footprints' span needs more than :data:`MAX_COVERAGE_CELLS`)."""
    polygons = [np.asarray(fp.polygon if isinstance(fp, Footprint) else fp, dtype=np.float64).reshape(-1, 2)
                for fp in prints.values()]
    polygons = [p for p in polygons if len(p) >= 3]
    if not polygons:
        return Coverage(np.zeros((0, 0), np.uint16), np.zeros(2), cell)
    allpts = np.vstack(polygons)
    # footprints kilometres apart (or a wrong scale) would need terabytes at the floor's cells: coarser cells keep
    # the raster at about MAX_COVERAGE_CELLS (a cell or two more per side)
    span = allpts.max(axis=0) - allpts.min(axis=0) + 2 * cell
    cell = max(cell, float(np.sqrt(span[0] * span[1] / MAX_COVERAGE_CELLS)))
    origin = np.floor(allpts.min(axis=0) / cell) * cell
    size = np.ceil((allpts.max(axis=0) - origin) / cell).astype(int) + 1
    counts = np.zeros((size[1], size[0]), np.uint16)
    shift = 8
    for polygon in polygons:
        mask = np.zeros_like(counts, dtype=np.uint8)
        vertices = np.round(((polygon - origin) / cell - 0.5) * (1 << shift)).astype(np.int32)
        cv2.fillPoly(mask, [vertices.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=shift)
        counts += mask
    return Coverage(counts, origin, cell)


def parse_heights(text: str, example: str = "0-2.2") -> tuple[float, float]:
    """A ``--heights`` option: ``"0-2.2"`` or ``"0,2.2"`` (metres above the floor) -> (0.0, 2.2); ``example``: the
    command's own default, shown in its messages."""
    text = text.strip()
    parts = text.split(",") if "," in text else text.split("-", 1) if not text.startswith("-") else None
    try:
        low, high = (float(p) for p in parts)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(f"--heights {text!r}: give two heights in metres above the floor, e.g. {example} or "
                         f"{example.replace('-', ',', 1)}") from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise InputError(f"--heights {text!r}: give two finite heights in metres above the floor, e.g. {example}")
    if not low < high:
        raise InputError(f"--heights {text!r}: the first height must be below the second (e.g. {example})")
    return low, high
