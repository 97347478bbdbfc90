"""Floor points the sparse model lacks, matched through a plane-induced warp.

Round an arena the cameras see the floor at grazing angles from azimuths tens of degrees apart: the floor's
texture is foreshortened differently in every view and SIFT matches almost none of it. With the poses known and a
rough floor plane, image ``j`` is warped into image ``i``'s view through the plane (ray of every pixel of i ->
plane -> projected into j with its lens model, ``cv2.remap``): on the floor the warped ``j`` looks like ``i``,
and SIFT matches: each feature of i with the warp's features anywhere (ratio test: a rough plane still matches)
and, for the features without such a match, among those within ``search_radius_px`` of the same pixel (where
the plane is right the floor is there). The warp only removes the perspective; the match positions are detected in ``i`` and in the
warped ``j`` and mapped back to ``j``'s own pixels, so the triangulated points do not depend on the guessed
plane (a guess a few decimetres or degrees off still matches). Matches whose triangulation reprojects worse
than ``max_reprojection_px`` in either image, lies behind a camera or meets at less than ``min_angle_deg`` are
dropped; images of the same rig are not paired (no baseline; the floor is static, so images of different frames
of different rigs are paired). Which of the rest are floor is :func:`rigsfm.run.world.floor_fit.fit_floor`'s job. The warp matches many times
the floor points plain SIFT does (see benchmarks/README.md).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from rigsfm.core.conventions import colmap_from_opencv_pixels, opencv_from_colmap_pixels
from rigsfm.core.errors import InputError
from rigsfm.core.geometry import project_world, triangulate_views
from rigsfm.core.image_files import read_image
from rigsfm.core.matching import candidate_matches
from rigsfm.core.names import name_of
from rigsfm.core.sift import detect, opencv_sift, reduction_factor

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FloorMatchOptions:
    sensors: tuple[str, ...] = ("wide",)  # which images take part (``<rig>/<sensor>/<file>``)
    max_distance: float = 40.0  # model units: pixels whose ray meets the plane farther away are ignored
    min_overlap_px: int = 5000  # pairs whose warped overlap is smaller are skipped
    max_ratio: float = 0.8
    contrast_threshold: float = 0.01  # OpenCV SIFT; lower than the default 0.04: floors are low-contrast
    # SIFT runs on the images (and warps) reduced by the integer factor that brings their longer side nearest
    # this (OpenCV's SIFT doubles its input first): 1624x1234 -> 2, 812x617 -> 1; faster, the floor as close to the
    # truth (see benchmarks/README.md).
    sift_size: int = 800
    max_features: int = 20000
    max_reprojection_px: float = 2.0
    min_angle_deg: float = 2.0  # triangulation angle; pairs of images of the same rig are never matched
    neighbours: int = 4  # each image is matched with the images of this many nearest rigs (0: all)
    # Also match each feature of i among the warp's features within this many pixels of it (the warp puts the
    # floor where it is in i; a guessed plane a few decimetres off shifts it by tens of pixels). 0: no.
    search_radius_px: float = 40.0


@dataclass(frozen=True)
class PairMatches:
    """The kept matches of one image pair (COLMAP pixels), to triangulate again once the poses move."""

    image_i: str
    image_j: str
    xy_i: np.ndarray  # Nx2
    xy_j: np.ndarray  # Nx2


@dataclass
class FloorMatches:
    points: np.ndarray  # Nx3 triangulated points (model frame), pair after pair in ``matches``' order
    pairs: dict[tuple[str, str], int] = field(default_factory=dict)  # image pair -> kept matches
    matches: list[PairMatches] = field(default_factory=list)  # the kept matches' pixels, in ``points``' order

    def __len__(self) -> int:
        return len(self.points)

    def groups(self) -> list[tuple[str, str]]:
        """The image pair of each point: its points share that pair's pose error (``fit_floor``'s groups)."""
        return [(m.image_i, m.image_j) for m in self.matches for _ in range(len(m.xy_i))]

    def triangulated_in(self, reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, list[tuple[str, str]]]:
        """The same matches triangulated with ``reconstruction``'s poses (the model adjusted again) and their image
        pairs; matches of images it lacks, or without a point, are left out."""
        images = {image.name: image for image in reconstruction.images.values() if image.has_pose}
        points, groups = [], []
        for m in self.matches:
            if m.image_i in images and m.image_j in images and len(m.xy_i):
                found = triangulate_pairs(images[m.image_i], images[m.image_j], m.xy_i, m.xy_j)
                found = found[np.isfinite(found).all(axis=1)]
                points.append(found)
                groups += [(m.image_i, m.image_j)] * len(found)
        return (np.vstack(points) if points else np.zeros((0, 3))), groups


GRID = 4  # px: rays and warp maps are computed on this grid and interpolated in between (cv2.remap)


def grid_rays(camera: pycolmap.Camera, step: int = GRID) -> tuple[np.ndarray, tuple[int, int]]:
    """Normalised camera coordinates (N x 2, row-major) of the OpenCV pixels (step k, step l) -- one more row and
    column than needed to cover the image, so interpolation never runs off the grid -- and the grid's shape."""
    shape = ((camera.height - 1) // step + 2, (camera.width - 1) // step + 2)
    xs, ys = np.meshgrid(np.arange(shape[1]) * step + 0.5, np.arange(shape[0]) * step + 0.5)
    normalised = camera.cam_from_img(np.stack([xs.ravel(), ys.ravel()], axis=1))
    return np.asarray(normalised, dtype=np.float64), shape


def plane_hits(image: pycolmap.Image, normal: np.ndarray, offset: float, max_distance: float,
               normalised: np.ndarray):
    """World point where each ray (``normalised`` camera coordinates, N x 2) meets the plane (N x 3) and whether
    it does so in front, within ``max_distance``."""
    dirs = np.c_[normalised, np.ones(len(normalised))] @ image.cam_from_world().rotation.matrix()
    centre = np.asarray(image.projection_center())
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(normal @ centre + offset) / (dirs @ normal)
    ok = np.isfinite(t) & (t > 0) & np.isfinite(dirs).all(axis=1)
    ok &= t * np.linalg.norm(dirs, axis=1) < max_distance
    return centre + np.where(ok, t, 0.0)[:, None] * dirs, ok


def warp_maps(hits: np.ndarray, ok: np.ndarray, target: pycolmap.Image, shape: tuple[int, int]):
    """Maps (OpenCV pixels of ``target``; -1e6 where none) of the plane points ``hits`` of the source image's
    rays, reshaped to ``shape``."""
    rows = np.flatnonzero(ok)
    pose = target.cam_from_world()
    in_target = hits[rows] @ pose.rotation.matrix().T + pose.translation
    front = in_target[:, 2] > 0
    rows, in_target = rows[front], in_target[front]
    map_x = np.full(len(hits), -1e6, np.float32)
    map_y = np.full(len(hits), -1e6, np.float32)
    if len(rows):
        # a model's images have their cameras; points in: pixels out
        uv = opencv_from_colmap_pixels(target.camera.img_from_cam(in_target))  # type: ignore[arg-type,union-attr]
        finite = np.isfinite(uv).all(axis=1)
        map_x[rows[finite]], map_y[rows[finite]] = uv[finite, 0], uv[finite, 1]
    return map_x.reshape(shape), map_y.reshape(shape)


def _inside(map_x: np.ndarray, map_y: np.ndarray, camera: pycolmap.Camera) -> np.ndarray:
    return (map_x >= 0) & (map_x <= camera.width - 1) & (map_y >= 0) & (map_y <= camera.height - 1)


@dataclass(frozen=True)
class PlaneWarp:
    """Image j seen from image i through a plane, over the part of i that sees j (``cv2.remap``)."""

    warped: np.ndarray  # j's pixels, resampled on i's pixel grid from (x0, y0)
    mask: np.ndarray  # uint8 255 where the warp lands inside j
    map_x: np.ndarray  # OpenCV pixels of j for each pixel of ``warped``
    map_y: np.ndarray
    origin: tuple[int, int]  # (x0, y0): OpenCV pixel of i of warped[0, 0]

    def covers(self, xy_i: np.ndarray) -> np.ndarray:
        """Which OpenCV pixels of i lie where the warp lands inside j."""
        local = np.round(np.asarray(xy_i).reshape(-1, 2)).astype(int) - self.origin
        height, width = self.mask.shape
        keep = (local[:, 0] >= 0) & (local[:, 0] < width) & (local[:, 1] >= 0) & (local[:, 1] < height)
        keep[keep] = self.mask[local[keep, 1], local[keep, 0]] > 0
        return keep

    def source_pixels(self, xy_warped: np.ndarray) -> np.ndarray:
        """COLMAP pixels of j of OpenCV pixels of ``warped``: a feature found in the warp is there in j."""
        xy = np.asarray(xy_warped, dtype=np.float64).reshape(-1, 2)
        if not len(xy):
            return np.zeros((0, 2))
        return colmap_from_opencv_pixels(np.c_[_sample(self.map_x, xy), _sample(self.map_y, xy)])


def plane_warp(hits: tuple[np.ndarray, np.ndarray], grid_shape: tuple[int, int], shape_i: tuple[int, int],
               image_j: pycolmap.Image, gray_j: np.ndarray, min_overlap_px: int = 0) -> PlaneWarp | None:
    """Warp ``gray_j`` into image i's view through the plane whose :func:`plane_hits` (on i's :func:`grid_rays`)
    are ``hits``; None when fewer than ``min_overlap_px`` pixels of i see j through it."""
    coarse = warp_maps(*hits, image_j, grid_shape)
    rows, cols = np.nonzero(_inside(*coarse, image_j.camera))  # type: ignore[call-arg]  # coarse: two maps
    if len(rows) * GRID**2 < max(min_overlap_px, 1):
        return None
    height, width = shape_i
    x0, x1 = max(0, (cols.min() - 1) * GRID), min(width, (cols.max() + 1) * GRID + 1)
    y0, y1 = max(0, (rows.min() - 1) * GRID), min(height, (rows.max() + 1) * GRID + 1)
    grid_x, grid_y = np.meshgrid(np.arange(x0, x1, dtype=np.float32) / GRID, np.arange(y0, y1, dtype=np.float32) / GRID)
    map_x, map_y = (cv2.remap(m, grid_x, grid_y, cv2.INTER_LINEAR) for m in coarse)
    inside = _inside(map_x, map_y, image_j.camera)  # type: ignore[arg-type]  # a model's images have their cameras
    warped = cv2.remap(gray_j, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return PlaneWarp(warped, inside.astype(np.uint8) * 255, map_x, map_y, (int(x0), int(y0)))


def _sample(map_: np.ndarray, xy: np.ndarray) -> np.ndarray:
    pts = xy.astype(np.float32).reshape(-1, 1, 2)
    return cv2.remap(map_, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR).reshape(-1)


def triangulate_pairs(image_i: pycolmap.Image, image_j: pycolmap.Image, xy_i: np.ndarray,
                      xy_j: np.ndarray) -> np.ndarray:
    """World points (N x 3; NaN where none) of matched COLMAP pixels of two posed images
    (:func:`rigsfm.core.geometry.triangulate_views`)."""
    # a model's images have their cameras
    rays = [np.asarray(image.camera.cam_from_img(np.asarray(xy, np.float64).reshape(-1, 2)), np.float64)  # type: ignore[union-attr]
            for image, xy in ((image_i, xy_i), (image_j, xy_j))]
    poses = np.stack([image_i.cam_from_world().matrix(), image_j.cam_from_world().matrix()])
    return triangulate_views(poses, np.tile([0, 1], (len(rays[0]), 1)), np.stack(rays, axis=1))


def _triangulate(image_i: pycolmap.Image, image_j: pycolmap.Image, xy_i: np.ndarray, xy_j: np.ndarray,
                 max_px: float, min_angle_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated points (COLMAP pixels in; every match's) and which of them to keep: those that reproject within
    ``max_px`` in both images and whose rays meet at ``min_angle_deg`` or more."""
    points = triangulate_pairs(image_i, image_j, xy_i, xy_j)
    good = np.isfinite(points).all(axis=1)
    rays = [points - image.projection_center() for image in (image_i, image_j)]
    with np.errstate(invalid="ignore"):
        cos = np.einsum("ij,ij->i", *rays) / (np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1))
        good &= np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) >= min_angle_deg
    for image, observed in ((image_i, xy_i), (image_j, xy_j)):
        # a model's images have their cameras
        xy, seen = project_world(image.camera, image.cam_from_world(), np.nan_to_num(points), margin_px=None)  # type: ignore[arg-type]
        with np.errstate(invalid="ignore"):
            good &= seen & (np.linalg.norm(xy - observed, axis=1) <= max_px)
    return points, good


@dataclass
class FloorImage:
    """One image taking part in floor matching: its pixels and its SIFT features (OpenCV pixels), extracted
    once and reused by every round and pair."""

    image: pycolmap.Image
    gray: np.ndarray
    xy: np.ndarray  # Nx2 OpenCV pixels
    descriptors: np.ndarray | None
    normalised: np.ndarray  # grid_rays of its camera
    grid_shape: tuple[int, int]
    sift_factor: int  # SIFT runs on it (and on warps into it) reduced by this (FloorMatchOptions.sift_size)


def _sift(options: FloorMatchOptions):
    return opencv_sift(options.max_features, options.contrast_threshold)


def load_floor_images(reconstruction: pycolmap.Reconstruction, image_dir: Path,
                      options: FloorMatchOptions | None = None, up: np.ndarray | None = None) -> list[FloorImage]:
    """One registered image per camera of ``options.sensors`` (the first frame: rigs are static and so is the
    floor), read from ``image_dir`` with its SIFT features (only where rays point down, against ``up``, if
    given: the floor is below the horizon)."""
    opt = options or FloorMatchOptions()
    image_dir = Path(image_dir)
    first: dict[int, pycolmap.Image] = {}
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if image.has_pose and str(name_of(image).sensor) in opt.sensors:
            first.setdefault(image.camera_id, image)
    sift = _sift(opt)
    result = []
    for image in sorted(first.values(), key=lambda im: im.name):
        path = image_dir / image.name
        gray = read_image(path, cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError(f"{path} cannot be read: floor matching needs the run's images (pass the IMAGES folder)")
        # a model's images have their cameras
        if gray.shape != (image.camera.height, image.camera.width):  # type: ignore[union-attr]
            raise InputError(f"{path} is {gray.shape[1]}x{gray.shape[0]}, its camera {image.camera.width}x"  # type: ignore[union-attr]
                             f"{image.camera.height}: pass the images the run used")  # type: ignore[union-attr]
        normalised, shape = grid_rays(image.camera)  # type: ignore[arg-type]
        mask = None
        if up is not None:  # below the horizon
            down = np.c_[normalised, np.ones(len(normalised))] @ (image.cam_from_world().rotation.matrix() @ up) < 0
            mask = cv2.resize(down.reshape(shape).astype(np.uint8) * 255, (shape[1] * GRID, shape[0] * GRID),
                              interpolation=cv2.INTER_NEAREST)[:gray.shape[0], :gray.shape[1]]
        factor = reduction_factor(gray.shape, opt.sift_size)
        xy, descriptors = detect(sift, gray, mask, factor)
        result.append(FloorImage(image, gray, xy, descriptors, normalised, shape, factor))
    return result


def neighbour_pairs(images: list[FloorImage], options: FloorMatchOptions | None = None) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of images of different rigs to match: each image with the images of the
    ``options.neighbours`` rigs nearest to it (camera centres; all pairs when ``neighbours`` is 0): rigs farther
    round match few floor points."""
    opt = options or FloorMatchOptions()
    rigs = [name_of(f.image).rig for f in images]
    candidates = [(i, j) for i, j in itertools.combinations(range(len(images)), 2) if rigs[i] != rigs[j]]
    if opt.neighbours <= 0:
        return candidates
    centres = np.array([f.image.projection_center() for f in images])
    chosen: set = set()
    for i in range(len(images)):
        nearest: dict[str, float] = {}
        for j in np.argsort(np.linalg.norm(centres - centres[i], axis=1), kind="stable"):
            if rigs[j] != rigs[i]:
                nearest.setdefault(rigs[j], float(np.linalg.norm(centres[j] - centres[i])))
        keep = set(list(nearest)[:opt.neighbours])
        chosen.update((min(i, j), max(i, j)) for j in range(len(images)) if rigs[j] in keep)
    return sorted(chosen)


def match_floor_points(reconstruction: pycolmap.Reconstruction, image_dir: Path | None, normal: np.ndarray,
                       offset: float, options: FloorMatchOptions | None = None, *,
                       images: list[FloorImage] | None = None) -> FloorMatches:
    """Match the floor between neighbouring registered images of ``options.sensors`` (:func:`neighbour_pairs`)
    through the plane ``normal @ x + offset = 0`` (model frame, a rough guess is enough) and triangulate the
    matches. ``images``: the :func:`load_floor_images` of an earlier round (read from ``image_dir`` if None)."""
    opt = options or FloorMatchOptions()
    if images is None:
        # images to match: a folder
        images = load_floor_images(reconstruction, image_dir, opt)  # type: ignore[arg-type]
    sift = _sift(opt)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    hits = {}
    points, counts, kept_matches = [], {}, []
    for a, b in neighbour_pairs(images, opt):
        first, second = images[a], images[b]
        image_i, image_j = first.image, second.image
        if first.descriptors is None or len(first.xy) < 2:
            continue
        if image_i.name not in hits:
            hits[image_i.name] = plane_hits(image_i, normal, offset, opt.max_distance, first.normalised)
        warp = plane_warp(hits[image_i.name], first.grid_shape, first.gray.shape, image_j, second.gray,
                          opt.min_overlap_px)
        if warp is None:
            continue
        xy_i, desc_i = first.xy, first.descriptors
        keep = warp.covers(xy_i)
        xy_i, desc_i = xy_i[keep], desc_i[keep]
        xy_w, desc_w = detect(sift, warp.warped, warp.mask, first.sift_factor)
        if desc_w is None or len(xy_w) < 2 or len(xy_i) < 2:
            continue
        xy_w = xy_w + warp.origin  # i's pixels
        pairs = matcher.knnMatch(desc_i, desc_w, k=2)  # anywhere: the plane may be a rough guess
        good = np.array([(m[0].queryIdx, m[0].trainIdx) for m in pairs
                         if len(m) == 2 and m[0].distance < opt.max_ratio * m[1].distance], int).reshape(-1, 2)
        if opt.search_radius_px > 0:  # and near the same pixel: where the plane is right, the floor is there
            near = cKDTree(xy_w).query_ball_point(xy_i, opt.search_radius_px)
            a = np.repeat(np.arange(len(xy_i)), [len(n) for n in near])  # type: ignore[assignment]  # here an array
            b = np.fromiter((k for n in near for k in n), dtype=np.int64, count=len(a))  # type: ignore[arg-type,assignment]
            local = candidate_matches(desc_i, desc_w, a, b, opt.max_ratio)  # type: ignore[arg-type]
            good = np.vstack([local, good[~np.isin(good[:, 0], local[:, 0])]])
        if not len(good):
            continue
        xy_j = warp.source_pixels(xy_w[good[:, 1]] - warp.origin)
        xy_i_colmap = colmap_from_opencv_pixels(xy_i[good[:, 0]])
        found, kept = _triangulate(image_i, image_j, xy_i_colmap, xy_j, opt.max_reprojection_px, opt.min_angle_deg)
        found = found[kept]
        counts[(image_i.name, image_j.name)] = len(found)
        points.append(found)
        kept_matches.append(PairMatches(image_i.name, image_j.name, xy_i_colmap[kept], xy_j[kept]))
        logger.debug("floor matching %s - %s: %d ratio-test matches, %d triangulated", image_i.name,
                     image_j.name, len(good), len(found))
    result = FloorMatches(np.vstack(points) if points else np.zeros((0, 3)), counts, kept_matches)
    logger.info("floor matching: %d points from %d image pairs", len(result), len(counts))
    return result
