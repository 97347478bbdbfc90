"""Narrow observations as correlated observations: a narrow pair's matches err alike over a region of the image.

A point seen only by narrow cameras (``--narrow``: a match between two synchronised narrow images, a 2-view track)
is one of a pair's matches, SIFT on a view warped through the floor. Their errors share a smooth part, a function of
the position in the image, and differ by a white part; and pairs far apart in azimuth are noisier than neighbours.
Counted as independent at the images' pooled weighting noise, a pair's shared error is taken for geometry and the
band does not allow for it. Per pair, from the adjusted model's own epipolar distances of its matches (not from any
truth): a quadratic in the position of the match in the first image fits the smooth part; the white part is the
fit's residual variance (its degrees of freedom counted), the smooth part what is left of the mean square beyond it.
Its ``n`` matches are then weighed like a camera's repeated views (:mod:`rigsfm.run.adjustment.repeated`):
correlation ``rho = smooth / (smooth + white)``, noise the pair's own ``sigma`` (per image coordinate, half the
epipolar distance's mean square) in place of the pooled one, inflated alike (``pixel_sigma_inflation``: the
adjustment absorbs a shared error into the geometry, so the residuals show less than the matches err; the smooth
part it absorbs is not seen here either, only what it leaves), so each of the pair's residuals weighs
``weight_sigma / (inflation sigma sqrt(1 + (n - 1) rho))`` of a pooled one. A pair noisier than the pooled noise
weighs less, a quieter one more; a longer track (one keypoint matched in several pairs) weighs the mean of its
pairs'. Where a pair's narrow calibration was held (``--fixed-calibration``), its smooth part is mostly that
calibration's error, which the consider covariance carries already: the white part alone weighs it. Only the
covariance uses it; the estimate is unchanged. A network without narrow-only points has nothing to weigh, so its
covariance is unchanged."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

logger = logging.getLogger(__name__)

MIN_PAIR_POINTS = 15  # a pair with fewer matches keeps the pooled weighting (too few to fit the smooth part)
POSITION_SCALE_PX = 100.0  # conditioning of the quadratic's columns


@dataclass(frozen=True)
class PairNoise:
    """One narrow pair's matches: how many, their noise per image coordinate (px), and their correlation."""

    images: tuple[int, int]
    points: int
    sigma_px: float
    rho: float
    white_px: float  # the white part alone, per image coordinate

    def weight(self, weight_sigma: float, inflation: float, held: bool = False) -> float:
        """Of each residual, against the pooled weighting noise ``weight_sigma`` (``inflation`` times the pooled
        noise: the pair's own noise is inflated alike). ``held``: a camera of the pair kept its calibration, whose
        error then makes most of the smooth part; the consider covariance carries it, so the white part alone."""
        if held:
            return weight_sigma / (inflation * self.white_px)
        return weight_sigma / (inflation * self.sigma_px * np.sqrt(1.0 + (self.points - 1) * self.rho))


def _narrow_points(reconstruction: pycolmap.Reconstruction, narrow_cameras: set[int]
                   ) -> tuple[dict[tuple[int, int], tuple[list[int], np.ndarray, np.ndarray]], dict[int, list[int]]]:
    """Points seen only by narrow cameras: per pair of narrow images its 2-view points (ids, keypoints in each
    image), and the longer tracks (a keypoint of one image matched in several pairs) with their images."""
    pairs: dict[tuple[int, int], tuple[list[int], list, list]] = {}
    longer: dict[int, list[int]] = {}
    for point_id, point in reconstruction.points3D.items():
        elements = sorted(point.track.elements, key=lambda e: e.image_id)
        images = [reconstruction.image(e.image_id) for e in elements]
        if len(elements) < 2 or not all(im.has_pose and im.camera_id in narrow_cameras for im in images):
            continue
        if len(elements) > 2:
            longer[point_id] = [e.image_id for e in elements]
            continue
        first, second = elements
        ids, xy_a, xy_b = pairs.setdefault((first.image_id, second.image_id), ([], [], []))
        ids.append(point_id)
        xy_a.append(np.asarray(images[0].points2D[first.point2D_idx].xy))
        xy_b.append(np.asarray(images[1].points2D[second.point2D_idx].xy))
    return {key: (ids, np.array(a), np.array(b)) for key, (ids, a, b) in pairs.items()}, longer


def _epipolar_distances(reconstruction: pycolmap.Reconstruction, image_a: int, image_b: int,
                        xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """Signed distances (px of b's focal length) of b's keypoints from the epipolar lines of a's, in the model."""
    a, b = reconstruction.image(image_a), reconstruction.image(image_b)
    b_from_a = b.cam_from_world() * a.cam_from_world().inverse()
    t = np.asarray(b_from_a.translation)
    essential = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ b_from_a.rotation.matrix()
    ray_a = np.c_[np.asarray(a.camera.cam_from_img(xy_a), dtype=np.float64), np.ones(len(xy_a))]  # type: ignore[union-attr]
    ray_b = np.c_[np.asarray(b.camera.cam_from_img(xy_b), dtype=np.float64), np.ones(len(xy_b))]  # type: ignore[union-attr]
    lines = ray_a @ essential.T
    focal = float(np.mean(b.camera.focal_length_x))  # type: ignore[union-attr]
    return focal * np.einsum("ij,ij->i", lines, ray_b) / np.hypot(lines[:, 0], lines[:, 1])


def pair_noise(distances: np.ndarray, xy: np.ndarray, images: tuple[int, int] = (0, 0)) -> PairNoise | None:
    """The smooth and white parts of one pair's epipolar distances (module docstring); None for too few matches
    or none finite."""
    ok = np.isfinite(distances) & np.isfinite(xy).all(axis=1)
    d, xy = distances[ok], xy[ok]
    n = len(d)
    if n < MIN_PAIR_POINTS:
        return None
    u = (xy - xy.mean(axis=0)) / POSITION_SCALE_PX
    design = np.c_[  # 1, x, y, x^2, xy, y^2 in the first image's position
        np.ones(n), u, u[:, 0] ** 2, u[:, 0] * u[:, 1], u[:, 1] ** 2]
    coef, *_ = np.linalg.lstsq(design, d, rcond=None)
    rank = np.linalg.matrix_rank(design)
    white = float(np.sum((d - design @ coef) ** 2)) / max(n - rank, 1)
    total = float(np.mean(d**2))
    if total <= 1e-18:  # exact matches: nothing to weigh
        return None
    smooth = max(total - white, 0.0)
    return PairNoise(images, n, float(np.sqrt(total / 2.0)), smooth / (smooth + white) if smooth + white > 0 else 0.0,
                     float(np.sqrt(max(white, 1e-18) / 2.0)))


def narrow_pair_noise(reconstruction: pycolmap.Reconstruction,
                      narrow_cameras: set[int]) -> tuple[list[PairNoise], dict[int, list[PairNoise]]]:
    """Every narrow pair's noise (pairs with at least ``MIN_PAIR_POINTS`` 2-view matches), and per point the pairs
    its images form (one for a 2-view point; a longer track's, where estimated)."""
    pairs_points, longer = _narrow_points(reconstruction, narrow_cameras)
    pairs, by_point, by_images = [], {}, {}
    for (image_a, image_b), (ids, xy_a, xy_b) in pairs_points.items():
        noise = pair_noise(_epipolar_distances(reconstruction, image_a, image_b, xy_a, xy_b), xy_a,
                           (image_a, image_b))
        if noise is None:
            continue
        pairs.append(noise)
        by_images[image_a, image_b] = noise
        by_point.update(dict.fromkeys(ids, [noise]))
    for point_id, images in longer.items():
        found = [by_images[a, b] for k, a in enumerate(images) for b in images[k + 1:] if (a, b) in by_images]
        if found:
            by_point[point_id] = found
    return pairs, by_point


def correlated_point_weights(reconstruction: pycolmap.Reconstruction, narrow_cameras: set[int],
                             point_ids: list[int], weight_sigma: float, inflation: float,
                             held_cameras: frozenset[int] | set[int] = frozenset()) -> np.ndarray | None:
    """Per point of ``point_ids`` (the Jacobian's point columns' order): the weight of its residuals, its pair's
    (a longer track: the mean of its pairs'; 1 for points of no estimated pair); None when no narrow pair has
    matches enough (nothing changes). ``held_cameras``: narrow cameras whose calibration the adjustment held
    (``PairNoise.weight``'s ``held``)."""
    pairs, by_point = narrow_pair_noise(reconstruction, narrow_cameras)
    if not pairs:
        return None
    rho = [p.rho for p in pairs]
    sigma = [p.sigma_px for p in pairs]
    logger.info("Covariance: %d narrow pairs' matches weighed as correlated (correlation %.2f-%.2f, median %.2f; "
                "noise %.2f-%.2f px against the pooled %.2f / %.1f)", len(pairs), min(rho), max(rho),
                float(np.median(rho)), min(sigma), max(sigma), weight_sigma / inflation, inflation)
    def held(noise: PairNoise) -> bool:
        return any(reconstruction.image(i).camera_id in held_cameras for i in noise.images)

    weights = {id(n): n.weight(weight_sigma, inflation, held(n)) for n in pairs}
    return np.array([np.mean([weights[id(n)] for n in by_point[p]]) if p in by_point else 1.0 for p in point_ids])
