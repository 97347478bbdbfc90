"""A world frame on the floor: z = 0 on the ground plane, z up, in the reconstruction's units (metres for
``OUT/sparse``).

Which sparse points are floor is decided from the geometry, not from labels:

1. **Up prior.** Cameras are mounted with small roll, so every camera's x axis is nearly horizontal: up is the
   direction most perpendicular to all x axes (smallest eigenvector of sum x x^T), signed to agree with the
   cameras' mean -y axis. When all x axes are parallel (every camera looks the same way) that eigenvector is
   undetermined and the prior falls back to the mean -y axis (off by the cameras' mean pitch, so the tilt
   allowed around it is widened).
2. **Candidates.** Points below the lowest camera along the prior (the floor is below every camera): sparse
   points (track >= 2, error <= 4 px), ``extra_points`` (floor matches, :mod:`rigsfm.run.world.floor_matching`:
   the sparse model of an arena often holds almost no floor, see there) and the end points of known-length
   markers (``markers``), which lie on the floor.
3. **RANSAC** (MSAC score) over planes whose normal is within ``max_tilt_deg`` of the prior, that have every
   camera above them and few points well below them (the floor is the lowest surface: at most
   ``max_below_fraction`` points per inlier more than max(3 thresholds, 5 % of the camera height) below).
   Walls, stands and pillar sides fail the tilt test; a ceiling fails "cameras above"; box tops and terraces
   have the floor (or the foot of the walls) below them. Triples are drawn until one lies on the best plane with
   99.9 % confidence (at most enough for a plane holding ``min_inlier_fraction`` of the candidates).
4. **Refinement.** Least-squares plane (SVD) on the inliers, re-thresholded at 3 robust sigmas (MAD) until
   the inlier set is stable. ``rms`` is the RMS point-to-plane residual of the final inliers.
5. **No floor.** Too few candidates, no valid hypothesis, fewer than ``min_points`` inliers, inliers covering
   fewer than ``min_cells`` cells of half the camera height (box tops, a platform), or many points well below
   the plane give :class:`NoFloor` with the reason; the caller warns and keeps the mapper's frame.
6. **Cost.** :func:`estimate_floor` reads images only when the sparse points and markers do not fix the floor
   (:func:`sparse_floor_shortfall`: fewer than 100 inliers, or standard errors of the normal above 0.02 deg or of
   a camera height above 0.2 % of it). Then floor matching (:mod:`rigsfm.run.world.floor_matching`) triangulates
   floor points between each wide image and those of its 4 nearest rigs, and stops as soon as the fit is
   precise enough. Rendered 8-rig arena (812x617, 2 busy cores): 6-10 s for all 28 pairs, one round; matching
   only the 2 nearest rigs (8 pairs) took 6 s and tilted the floor 0.13 deg (each pair's points lie in one
   region, offset by that pair's pose errors: more pairs average them). 4 nearest rigs against 6 (the same
   arena with exact and realistic rigs.yaml, full-size 8- and 16-rig circles): floor normal within 0.006 deg and
   median camera heights within 1.3 mm of 6's, neither better throughout; 16 rigs: 32 instead of 48 pairs, 1.5 s
   less.

The frame: z = the plane's upward normal; origin = the orthogonal projection onto the plane of the centroid of
the rig positions (a rig's position = its reference (wide) camera centre, averaged over its registered
frames); x axis = horizontal direction from the origin towards the first rig (lowest rig id, i.e. the first
rig of rigs.yaml, or the rig named by ``x_towards``); y = z x x (right-handed). If the first rig stands over the
origin (a single rig), x follows its wide camera's viewing direction projected on the floor.

``FloorFit.floor_from_model`` is a ``pycolmap.Rigid3d``; apply it with :func:`apply_floor_frame`, which calls
``Reconstruction.transform`` with a scale-1 ``Sim3d``. COLMAP's ``Reconstruction::Transform`` multiplies every
non-reference ``sensor_from_rig`` translation by the similarity's scale, so scale 1 leaves E^sl untouched (a
metric model must never be re-scaled here: the metres come from ``rigsfm.scale``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from rigsfm.core.names import name_of
from rigsfm.run.adjustment.scale import triangulate_observed_point
from rigsfm.run.inputs.scale_file import ScaleSpec

logger = logging.getLogger(__name__)


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
    normal_sigma_deg: float = float("inf")  # standard error of the normal's tilt (largest axis), from the inliers
    height_sigma: float = float("inf")  # largest standard error of a camera's height, from the inliers

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
            "marker_residuals": self.marker_residuals,
            "warnings": list(self.warnings),
        }


# --- geometry helpers -------------------------------------------------------------------------------------


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through Nx3 points: unit normal n and offset d with n @ x + d = 0."""
    p = np.asarray(points, dtype=np.float64)
    centroid = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centroid, full_matrices=False)
    normal = vt[-1]
    return normal, float(-normal @ centroid)


def _posed_images(reconstruction: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted((im for im in reconstruction.images.values() if im.has_pose), key=lambda im: im.name)


def up_prior(reconstruction: pycolmap.Reconstruction) -> tuple[np.ndarray, str]:
    """The cameras' common up direction (unit, model frame) and how it was found (see the module docstring)."""
    images = _posed_images(reconstruction)
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


# --- the fit ----------------------------------------------------------------------------------------------


FIRST_TRIPLES = 100  # RANSAC's first batch; then batches double up to FloorOptions.ransac_iterations


def _ransac(points: np.ndarray, up: np.ndarray, max_tilt_deg: float, centres: np.ndarray, threshold: float,
            margin: float, max_below_fraction: float, iterations: int, rng: np.random.Generator,
            min_inlier_fraction: float, confidence: float = 0.999) -> tuple[np.ndarray, float] | None:
    """Best plane (MSAC) among random triples whose normal is near ``up``, that has every centre above it and
    fewer than ``max_below_fraction`` points per inlier more than ``margin`` below it.

    Triples are drawn in batches (``FIRST_TRIPLES``, doubling up to ``iterations``) until, with ``confidence``,
    one of them lies on the best plane found (adaptive RANSAC: ``log(1 - confidence) / log(1 - w^3)`` triples
    for its inlier fraction w), or on a plane holding ``min_inlier_fraction`` of the points when none is found.
    A first batch of 3000 cost 0.5 s on the 13 000 floor matches of a 16-rig circle, where 10 triples were
    needed. A fixed 3000 missed the floor of the rendered 3-rig arc about one time in three: ~40 floor points
    among 550 candidates, 1.2 all-floor triples expected in 3000; which run missed it depended on pose changes
    of 1e-5 deg."""
    n = len(points)

    def needed(fraction: float) -> int:
        if fraction >= 1.0:  # every candidate on the plane: one triple
            return 1
        return int(np.ceil(np.log(1.0 - confidence) / np.log1p(-max(fraction, 1e-9) ** 3)))

    best, best_cost, best_inliers, drawn = None, np.inf, 0, 0
    t2 = threshold**2
    degenerate = 1e-12 * max(1.0, float(np.abs(points).max())) ** 2  # |normal| of three collinear points
    min_cos_tilt = np.cos(np.radians(max_tilt_deg))
    while drawn < needed(max(best_inliers / n, min_inlier_fraction)):
        batch = min(iterations, max(FIRST_TRIPLES, drawn))  # doubling: a plane holding most points stops early
        triples = rng.integers(0, n, size=(batch, 3))
        drawn += batch
        a, b, c = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
        normals = np.cross(b - a, c - a)
        norms = np.linalg.norm(normals, axis=1)
        ok = norms > degenerate
        normals[ok] /= norms[ok, None]
        normals *= np.sign(normals @ up)[:, None]
        ok &= normals @ up >= min_cos_tilt
        offsets = -np.einsum("ij,ij->i", normals, a)
        ok &= (centres @ normals.T + offsets).min(axis=0) > threshold
        normals, offsets = normals[ok], offsets[ok]
        for start in range(0, len(normals), 256):
            r = points @ normals[start:start + 256].T + offsets[start:start + 256]
            cost = np.minimum(r**2, t2).sum(axis=0)
            below = (r < -margin).sum(axis=0)
            inliers = (np.abs(r) < threshold).sum(axis=0)
            cost[below > max_below_fraction * inliers] = np.inf
            k = int(np.argmin(cost))
            if np.isfinite(cost[k]) and cost[k] < best_cost:
                best_cost, best, best_inliers = cost[k], (normals[start + k], float(offsets[start + k])), int(inliers[k])
    return best


def _refine(points: np.ndarray, normal: np.ndarray, offset: float, up: np.ndarray, threshold: float,
            max_rounds: int = 20) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Iterate LSQ fit on inliers and threshold = 3 robust sigmas, the sigma from the points within 3 RANSAC
    thresholds (floor matches of different image pairs are offset from each other by the pose errors, up to
    +-4 cm with a realistic rigs.yaml: a threshold from the inliers alone shrank onto a few pairs and tilted
    the floor by 0.2 deg)."""
    inliers = np.abs(points @ normal + offset) < threshold
    t = threshold
    for _ in range(max_rounds):
        if inliers.sum() < 3:
            break
        normal, offset = fit_plane(points[inliers])
        if normal @ up < 0:
            normal, offset = -normal, -offset
        r = points @ normal + offset
        near = np.abs(r) < 3.0 * threshold
        sigma = 1.4826 * float(np.median(np.abs(r[near])))
        t = float(np.clip(3.0 * sigma, threshold, 3.0 * threshold))
        new = np.abs(r) < t
        if np.array_equal(new, inliers):
            break
        inliers = new
    return normal, offset, inliers, t


def plane_precision(points: np.ndarray, normal: np.ndarray, sigma: float,
                    centres: np.ndarray) -> tuple[float, float]:
    """Standard errors of a least-squares plane through ``points`` with residual noise ``sigma``: of its
    normal's tilt (degrees, the worse axis) and of the heights of ``centres`` above it (the largest).

    Height above the plane near the points' centroid c: h(x) = e + a u + b v, (u, v) in-plane coordinates of
    x - c; cov(e) = sigma^2 / N, cov(a, b) = sigma^2 (sum of [u v]^T [u v])^-1; (a, b) is the tilt in radians."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3 or not np.isfinite(sigma):
        return float("inf"), float("inf")
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    centroid = p.mean(axis=0)
    uv = (p - centroid) @ np.stack([a, b]).T
    scatter = uv.T @ uv
    if np.linalg.cond(scatter) > 1e12:
        return float("inf"), float("inf")
    tilt = sigma**2 * np.linalg.inv(scatter)
    normal_sigma = float(np.degrees(np.sqrt(np.linalg.eigvalsh(tilt).max())))
    at = (np.asarray(centres, dtype=np.float64).reshape(-1, 3) - centroid) @ np.stack([a, b]).T
    variance = sigma**2 / len(p) + np.einsum("ij,jk,ik->i", at, tilt, at)
    return normal_sigma, float(np.sqrt(variance.max())) if len(at) else float("inf")


def _occupied_cells(points: np.ndarray, normal: np.ndarray, cell: float) -> int:
    """How many square cells of side ``cell`` of the plane (normal ``normal``) the points fall in."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    ij = np.floor(np.c_[points @ a, points @ b] / cell).astype(np.int64)
    return len(np.unique(ij, axis=0))


def _floor_frame(normal: np.ndarray, offset: float, reconstruction: pycolmap.Reconstruction,
                 x_towards: str | None) -> tuple[pycolmap.Rigid3d, str]:
    rigs = rig_positions(reconstruction)
    centroid = np.mean([c for _, c in rigs.values()], axis=0)
    origin = centroid - (normal @ centroid + offset) * normal
    if x_towards is None:
        name, target = next(iter(rigs.values()))
    else:
        matches = [(n, c) for n, c in rigs.values() if n == x_towards]
        if not matches:
            raise ValueError(f"x_towards={x_towards!r} is not a registered rig ({', '.join(n for n, _ in rigs.values())})")
        name, target = matches[0]
    x = target - origin
    x -= (x @ normal) * normal
    if np.linalg.norm(x) < 1e-9 * max(1.0, float(np.linalg.norm(target))):
        image = next(im for im in _posed_images(reconstruction)
                     if name_of(im).rig == name and not name_of(im).is_narrow)
        x = np.asarray(image.viewing_direction(), dtype=np.float64)
        x -= (x @ normal) * normal
    x /= np.linalg.norm(x)
    y = np.cross(normal, x)
    rotation = np.stack([x, y, normal])  # rows: floor axes in model coordinates
    floor_from_model = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ origin)
    return floor_from_model, name


def fit_floor(reconstruction: pycolmap.Reconstruction, markers: np.ndarray | None = None,
              options: FloorOptions | None = None, *, extra_points: np.ndarray | None = None,
              x_towards: str | None = None, quiet: bool = False) -> FloorFit | NoFloor:
    """Fit the floor plane to the sparse points, ``extra_points`` (e.g. from
    :func:`rigsfm.run.world.floor_matching.match_floor_points`) and ``markers`` (model-frame points known to be on
    the floor), and define the floor frame (module docstring). Returns :class:`NoFloor` with the reason when
    the scene has no detectable floor. ``quiet``: leave the warnings in the result, unlogged."""
    opt = options or FloorOptions()
    images = _posed_images(reconstruction)
    if len(images) < 1:
        return NoFloor("no registered image")
    up, prior_source = up_prior(reconstruction)
    max_tilt = opt.max_tilt_deg if prior_source == "camera x axes" else min(2.0 * opt.max_tilt_deg, 60.0)
    centres = np.array([im.projection_center() for im in images])
    lowest = float((centres @ up).min())

    ids, xyz = [], []
    for point_id, point in reconstruction.points3D.items():
        if point.track.length() >= opt.min_track_length and point.error <= opt.max_reprojection_error:
            ids.append(point_id)
            xyz.append(point.xyz)
    ids = np.asarray(ids, dtype=np.int64)  # type: ignore[assignment]  # here an array
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)  # type: ignore[assignment]
    below = xyz @ up < lowest
    ids, xyz = ids[below], xyz[below]
    markers = np.zeros((0, 3)) if markers is None else np.asarray(markers, dtype=np.float64).reshape(-1, 3)
    extra = np.zeros((0, 3)) if extra_points is None else np.asarray(extra_points, dtype=np.float64).reshape(-1, 3)
    extra = extra[extra @ up < lowest]
    points = np.vstack([xyz, extra, markers])
    source = np.repeat(np.array(["sparse", "matched", "markers"]), [len(xyz), len(extra), len(markers)])
    is_marker = source == "markers"
    if len(points) < opt.min_points:
        return NoFloor(f"only {len(points)} sparse points lie below the cameras (need {opt.min_points}): "
                       "the floor is not textured or not seen")

    depth_below = lowest - points @ up
    scale = float(np.median(depth_below))  # ~ the camera height when most points are on the floor
    threshold = opt.threshold if opt.threshold is not None else 0.01 * scale
    margin = max(3 * threshold, 0.05 * scale)
    rng = np.random.default_rng(opt.seed)
    best = _ransac(points, up, max_tilt, centres, threshold, margin, opt.max_below_fraction,
                   opt.ransac_iterations, rng, opt.min_inlier_fraction)
    if best is None:
        return NoFloor(f"no plane within {max_tilt:.0f} deg of the cameras' up direction has all cameras above it "
                       "and few points below it")
    normal, offset, inliers, t = _refine(points, *best, up, threshold)
    count = int(inliers.sum())
    if count < opt.min_points or count < opt.min_inlier_fraction * len(points):
        return NoFloor(f"the best floor candidate holds {count} of the {len(points)} points below the cameras "
                       f"(need {opt.min_points} and {100 * opt.min_inlier_fraction:.0f} %)")
    heights_of_centres = centres @ normal + offset
    if heights_of_centres.min() <= 0:
        return NoFloor("the best floor candidate has a camera below it")
    median_height = float(np.median(heights_of_centres))
    cells = _occupied_cells(points[inliers], normal, median_height / 2)
    if cells < opt.min_cells:
        return NoFloor(f"the best floor candidate ({count} points) covers only {cells} cells of "
                       f"{median_height / 2:.3g} x {median_height / 2:.3g} (half the camera height; need "
                       f"{opt.min_cells}): box tops or a platform, not the floor")
    r = points @ normal + offset
    below_fraction = float(np.sum(r < -max(3 * t, 0.05 * median_height)) / count)
    if below_fraction > opt.max_below_fraction:
        return NoFloor(f"the best floor candidate has {100 * below_fraction:.0f} % as many points well below it as "
                       "on it: it is not the lowest surface (no floor seen, or a floor reflecting the scene)")
    residuals = r[inliers]
    rms = float(np.sqrt(np.mean(residuals**2)))
    robust_sigma = 1.4826 * float(np.median(np.abs(residuals)))
    warnings = []
    if below_fraction > 0.2:
        warnings.append(f"{100 * below_fraction:.0f} % as many points lie well below the floor as on it: a pit, "
                        "stands below floor level, or reflections in a glossy floor?")
    marker_residuals = [float(v) for v in r[is_marker]]
    far = [v for v in marker_residuals if abs(v) > 3 * t]
    if far:
        warnings.append(f"{len(far)} known-length end point(s) are off the floor by up to {max(map(abs, far)):.3g}: "
                        "are the markers on the floor?")
    angle = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
    normal_sigma, height_sigma = plane_precision(points[inliers], normal, max(robust_sigma, rms / 3), centres)
    floor_from_model, origin_rig = _floor_frame(normal, offset, reconstruction, x_towards)
    for w in warnings if not quiet else ():
        logger.warning("floor: %s", w)
    logger.info("floor: %d of %d points below the cameras, RMS %.3g, normal %.2f deg from the %s", count,
                len(points), rms, angle, prior_source)
    return FloorFit(
        normal=normal, offset=float(offset), rms=rms, robust_sigma=robust_sigma, threshold=t, num_points=count,
        num_candidates=len(points),
        points_by_source={k: int(np.sum(inliers & (source == k))) for k in ("sparse", "matched", "markers")},
        up_prior=up, up_prior_source=prior_source, prior_angle_deg=angle,
        floor_from_model=floor_from_model, origin_rig=origin_rig,
        camera_heights={im.name: float(h) for im, h in zip(images, heights_of_centres)},
        marker_residuals=marker_residuals, below_fraction=below_fraction,
        inlier_ids=ids[inliers[: len(ids)]], warnings=tuple(warnings),
        normal_sigma_deg=normal_sigma, height_sigma=height_sigma,
    )


def apply_floor_frame(reconstruction: pycolmap.Reconstruction, fit: FloorFit) -> None:
    """Move ``reconstruction`` into the floor frame in place (scale 1: ``sensor_from_rig`` is unchanged)."""
    transform = fit.floor_from_model
    reconstruction.transform(pycolmap.Sim3d(1.0, transform.rotation, transform.translation))


def axes_convergence(reconstruction: pycolmap.Reconstruction) -> np.ndarray | None:
    """The point closest (least squares) to every registered camera's optical axis, or None when the axes do
    not converge in front of every camera. Crowd rigs aim at the floor, so this is a point near it."""
    images = _posed_images(reconstruction)
    if len(images) < 2:
        return None
    a, b = np.zeros((3, 3)), np.zeros(3)
    for image in images:
        d = np.asarray(image.viewing_direction(), dtype=np.float64)
        projector = np.eye(3) - np.outer(d, d)
        a += projector
        b += projector @ image.projection_center()
    if np.linalg.cond(a) > 1e8:
        return None
    point = np.linalg.solve(a, b)
    in_front = all((point - im.projection_center()) @ im.viewing_direction() > 0 for im in images)
    return point if in_front else None


def guess_floor(reconstruction: pycolmap.Reconstruction, markers: np.ndarray | None = None,
                options: FloorOptions | None = None) -> tuple[np.ndarray, float, str] | NoFloor:
    """A rough floor plane (normal, offset, how) to warp images with, in order of preference: a floor fitted
    to the sparse points; the up prior through the markers' mean height; the up prior through the 2nd
    percentile of the heights of the sparse points below the cameras (the floor is the lowest large surface);
    the up prior through the point where the cameras' optical axes converge, if it lies below every camera."""
    fit = fit_floor(reconstruction, markers, options, quiet=True)
    if fit:
        return fit.normal, fit.offset, "sparse points"  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
    up, _ = up_prior(reconstruction)
    if markers is not None and len(markers):
        return up, -float(np.mean(np.asarray(markers).reshape(-1, 3) @ up)), "markers and the cameras' up"
    lowest = float(min(im.projection_center() @ up for im in _posed_images(reconstruction)))
    heights = np.array([p.xyz for p in reconstruction.points3D.values()]).reshape(-1, 3) @ up
    heights = heights[heights < lowest]
    if len(heights) >= (options or FloorOptions()).min_points:
        return up, -float(np.percentile(heights, 2.0)), "lowest sparse points and the cameras' up"
    point = axes_convergence(reconstruction)
    if point is not None and point @ up < lowest:
        return up, -float(point @ up), "convergence of the optical axes and the cameras' up"
    # FloorFit is truthy: a NoFloor here
    return NoFloor(f"{fit.reason}; no marker, {len(heights)} sparse points below the cameras and no convergence "  # type: ignore[union-attr]
                   "of the optical axes below them to guess the floor height from")


@dataclass(frozen=True)
class FloorEstimate:
    """What :func:`estimate_floor` found and what it cost."""

    fit: FloorFit | NoFloor
    why_matched: str | None = None  # why the sparse points were not enough (None: no floor matching ran)
    rounds: int = 0  # floor-matching rounds
    pairs: int = 0  # image pairs matched, over all rounds
    matched_points: int = 0  # triangulated floor matches of the last round
    seconds: float = 0.0  # floor matching (reading images, SIFT, warps, triangulation)


def sparse_floor_shortfall(fit: FloorFit | NoFloor, reconstruction: pycolmap.Reconstruction,
                           options: FloorOptions | None = None) -> str | None:
    """Why a floor fitted to the sparse points (and markers) alone is not enough, or None when it is: it
    needs ``enough_points`` inliers and standard errors of its normal below ``enough_normal_sigma_deg``
    and of the camera heights below ``enough_height_sigma`` x the median camera height."""
    opt = options or FloorOptions()
    if not fit:
        # FloorFit is truthy: a NoFloor here
        return f"no floor in the sparse points ({fit.reason})"  # type: ignore[union-attr]
    # NoFloor is falsy: a FloorFit here
    median_height = float(np.median(list(fit.camera_heights.values())))  # type: ignore[union-attr]
    if fit.num_points < opt.enough_points:  # type: ignore[union-attr]
        return f"{fit.num_points} sparse floor points (want {opt.enough_points})"  # type: ignore[union-attr]
    if fit.normal_sigma_deg > opt.enough_normal_sigma_deg:  # type: ignore[union-attr]
        return f"their normal is uncertain by {fit.normal_sigma_deg:.3f} deg (want {opt.enough_normal_sigma_deg})"  # type: ignore[union-attr]
    if fit.height_sigma > opt.enough_height_sigma * median_height:  # type: ignore[union-attr]
        return (f"camera heights uncertain by {fit.height_sigma:.3g} (want "  # type: ignore[union-attr]
                f"{opt.enough_height_sigma * median_height:.3g})")
    return None


def estimate_floor(reconstruction: pycolmap.Reconstruction, image_dir=None, markers: np.ndarray | None = None,
                   options: FloorOptions | None = None, match_options=None, *, x_towards: str | None = None,
                   max_rounds: int = 3) -> FloorEstimate:
    """The floor from everything available, cheapest first: the sparse points and markers alone when they
    fix it precisely enough (:func:`sparse_floor_shortfall`); otherwise, when ``image_dir`` is given, guess a
    plane (:func:`guess_floor`), match the floor between neighbouring images through it
    (:mod:`rigsfm.run.world.floor_matching`), fit the floor to the sparse, matched and marker points, and match
    again through the fitted plane while it moved by more than 0.05 deg or 0.5 % of the camera height from
    the plane the matching used (at most ``max_rounds`` matchings: a guess 14 cm off gave 530 matches, 262 on
    the floor; the second round through the fit 679 and 391)."""
    import time

    from rigsfm.run.world.floor_matching import load_floor_images, match_floor_points

    opt = options or FloorOptions()
    sparse = fit_floor(reconstruction, markers, opt, x_towards=x_towards, quiet=True)
    shortfall = sparse_floor_shortfall(sparse, reconstruction, opt)
    if shortfall is None or image_dir is None:
        # NoFloor is falsy: a FloorFit here
        for warning in sparse.warnings if sparse else ():  # type: ignore[union-attr]
            logger.warning("floor: %s", warning)
        return FloorEstimate(sparse, why_matched=None)
    logger.info("floor: matching the floor between images (%s)", shortfall)
    start = time.perf_counter()
    # NoFloor is falsy: a FloorFit here
    guess = (sparse.normal, sparse.offset, "sparse points") if sparse else guess_floor(reconstruction, markers, opt)  # type: ignore[union-attr]
    if not guess:
        return FloorEstimate(guess, shortfall, seconds=time.perf_counter() - start)
    normal, offset, how = guess  # type: ignore[misc]  # NoFloor is falsy: a tuple here
    logger.info("floor guess from the %s", how)
    centres = np.array([im.projection_center() for im in _posed_images(reconstruction)])
    images = load_floor_images(reconstruction, image_dir, match_options, up=normal)
    fit: FloorFit | NoFloor = NoFloor("no matching round ran")
    rounds = pairs = found = 0
    for _ in range(max(1, max_rounds)):
        matches = match_floor_points(reconstruction, image_dir, normal, offset, match_options, images=images)
        rounds, pairs, found = rounds + 1, pairs + len(matches.pairs), len(matches)
        fit = fit_floor(reconstruction, markers, opt, extra_points=matches.points, x_towards=x_towards, quiet=True)
        if not fit or sparse_floor_shortfall(fit, reconstruction, opt) is None:
            break  # no floor, or precise enough
        # NoFloor is falsy: a FloorFit here
        moved_deg = float(np.degrees(np.arccos(np.clip(fit.normal @ normal, -1.0, 1.0))))  # type: ignore[union-attr]
        moved = float(np.max(np.abs(fit.height(centres) - (centres @ normal + offset))))  # type: ignore[union-attr]
        if moved_deg <= 0.05 and moved <= 0.005 * float(np.median(fit.height(centres))):  # type: ignore[union-attr]
            break
        logger.info("floor moved by %.3f deg / %.3g at the cameras from the matching plane", moved_deg, moved)
        normal, offset = fit.normal, fit.offset  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
    if not fit and sparse:
        fit = sparse  # the matches did not help: keep the sparse floor
    for warning in fit.warnings if fit else ():  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
        logger.warning("floor: %s", warning)
    seconds = time.perf_counter() - start
    logger.info("floor matching: %d round(s), %d image pairs, %.1f s", rounds, pairs, seconds)
    return FloorEstimate(fit, shortfall, rounds, pairs, found, seconds)
