"""The robust floor fit (``rigsfm.run.world.floor``'s steps 2-5): RANSAC over tilted-plane hypotheses, the
refinement, its precision and the floor frame."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import pycolmap

from rigsfm.core.names import ImageName, name_of
from rigsfm.run.world.floor_model import (
    FloorFit,
    FloorOptions,
    NoFloor,
    fit_plane,
    posed_images,
    rig_positions,
    up_prior,
)

logger = logging.getLogger(__name__)


MIN_GROUPS = 6  # image pairs below which the floor's tilt and sigma are weakly determined (grouped_plane_precision)
FIRST_TRIPLES = 100  # RANSAC's first batch; then batches double up to FloorOptions.ransac_iterations


def _ransac(points: np.ndarray, up: np.ndarray, max_tilt_deg: float, centres: np.ndarray, threshold: float,
            margin: float, max_below_fraction: float, iterations: int, rng: np.random.Generator,
            min_inlier_fraction: float, confidence: float = 0.999) -> tuple[np.ndarray, float] | None:
    """Best plane (MSAC) among random triples whose normal is near ``up``, that has every centre above it and
    fewer than ``max_below_fraction`` points per inlier more than ``margin`` below it.

    Triples are drawn in batches (``FIRST_TRIPLES``, doubling up to ``iterations``) until, with ``confidence``,
    one of them lies on the best plane found (adaptive RANSAC: ``log(1 - confidence) / log(1 - w^3)`` triples
    for its inlier fraction w), or on a plane holding ``min_inlier_fraction`` of the points when none is found.
    A large fixed batch wastes time where a few triples suffice, and a fixed count misses a floor that holds a small
    share of the candidates (a small arc), depending on tiny pose changes."""
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


def grouped_plane_precision(points: np.ndarray, groups: np.ndarray, normal: np.ndarray, offset: float,
                            centres: np.ndarray) -> dict:
    """Standard errors of the least-squares plane through ``points`` (as :func:`plane_precision`'s) where the points
    of one group (``groups``: a label per point; the image pair that triangulated them) share an offset from the
    plane: that pair's pose error moves all its points together, so they are not independent draws.

    Model: height residual r_i = b_g + e_i, b_g ~ (0, sigma_b^2) per group, e_i ~ (0, sigma_e^2). Both variances are
    the unbiased moment estimates from the residuals' between-group and within-group sums of squares, their
    expectations taken through the plane fit (which absorbs three of the groups' offsets: a plane through three
    patches leaves them no residual). The plane's covariance is then the OLS sandwich under that model,
    (X^T X)^-1 X^T V X (X^T X)^-1 with V = sigma_e^2 I + sigma_b^2 Z Z^T. Needs four groups or more (the between-group
    variance has ``num_groups`` - 3 degrees of freedom); with fewer the sigmas are infinite."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    _, labels = np.unique(np.asarray(groups), return_inverse=True)
    labels = labels.reshape(-1)
    n = np.bincount(labels).astype(np.float64)
    k, count = len(n), len(p)
    result = {"normal_sigma_deg": float("inf"), "height_sigma": float("inf"), "group_sigma": float("inf"),
              "height_sigmas": np.full(len(np.asarray(centres).reshape(-1, 3)), np.inf),
              "point_sigma": float("nan"), "num_groups": int(k),
              "effective_groups": float(count**2 / np.sum(n**2)) if count else 0.0}
    if count < 4 or k < 4:
        return result
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    centroid = p.mean(axis=0)
    x = np.c_[np.ones(count), (p - centroid) @ np.stack([a, b]).T]  # height = e + tilt_a u + tilt_b v
    r = p @ normal + offset
    xtx = x.T @ x
    if np.linalg.cond(xtx) > 1e12:
        return result
    inv = np.linalg.inv(xtx)
    s = np.stack([np.bincount(labels, weights=x[:, j], minlength=k) for j in range(3)])  # X^T Z
    sums = np.bincount(labels, weights=r, minlength=k)
    between = float(np.sum(sums**2 / n))  # r^T P_Z r
    within = float(r @ r) - between
    g = np.diag(n) - s.T @ inv @ s  # Z^T M Z
    t_pm = k - float(np.trace(inv @ (s / n) @ s.T))  # tr(P_Z M)
    t_gdg = float(np.trace(g @ (g / n[:, None])))  # tr(Z^T M P_Z M Z)
    system = np.array([[t_pm, t_gdg], [count - 3 - t_pm, float(np.trace(g)) - t_gdg]])
    try:
        point_var, group_var = np.linalg.solve(system, [between, within])
    except np.linalg.LinAlgError:
        return result
    if group_var < 0:  # the groups agree better than their points: no shared offset seen
        point_var, group_var = float(r @ r) / (count - 3), 0.0
    point_var = max(float(point_var), 0.0)
    cov = inv @ (point_var * xtx + group_var * s @ s.T) @ inv
    normal_sigma = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[1:, 1:]).max(), 0.0))))
    at = np.c_[np.ones(len(centres)), (np.asarray(centres, dtype=np.float64).reshape(-1, 3) - centroid)
               @ np.stack([a, b]).T]
    variance = np.einsum("ij,jk,ik->i", at, cov, at)
    result.update(normal_sigma_deg=normal_sigma, height_sigma=float(np.sqrt(variance.max())) if len(at) else float("inf"),
                  height_sigmas=np.sqrt(np.maximum(variance, 0.0)),
                  group_sigma=float(np.sqrt(group_var)), point_sigma=float(np.sqrt(point_var)))
    return result


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
        image = next(im for im in posed_images(reconstruction)
                     if name_of(im).rig == name and not name_of(im).is_narrow)
        x = np.asarray(image.viewing_direction(), dtype=np.float64)
        x -= (x @ normal) * normal
    x /= np.linalg.norm(x)
    y = np.cross(normal, x)
    rotation = np.stack([x, y, normal])  # rows: floor axes in model coordinates
    floor_from_model = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ origin)
    return floor_from_model, name


def _simultaneous(track: pycolmap.Track, frame_of: dict[int, str]) -> bool:
    """Whether two images of one frame saw the point: a track that joins only different frames may be a walking
    person seen at two instants, triangulated anywhere (under the floor too)."""
    frames = [frame_of.get(element.image_id, "") for element in track.elements]
    return len(set(frames)) < len(frames)


def _rig_pair(names: Sequence[str]) -> str:
    """The group of a point seen in these images: the first two rigs (sorted), whose poses its error shares."""
    rigs = sorted(dict.fromkeys(ImageName.parse(name).rig for name in names))
    return "|".join(rigs[:2])


def fit_floor(reconstruction: pycolmap.Reconstruction, markers: np.ndarray | None = None,
              options: FloorOptions | None = None, *, extra_points: np.ndarray | None = None,
              extra_groups: Sequence[tuple[str, str]] | None = None,
              x_towards: str | None = None, quiet: bool = False) -> FloorFit | NoFloor:
    """Fit the floor plane to the sparse points, ``extra_points`` (e.g. from
    :func:`rigsfm.run.world.floor_matching.match_floor_points`; ``extra_groups``: the image pair of each, its
    ``groups()``) and ``markers`` (model-frame points known to be on the floor), and define the floor frame (module
    docstring). Returns :class:`NoFloor` with the reason when the scene has no detectable floor. ``quiet``: leave
    the warnings in the result, unlogged."""
    opt = options or FloorOptions()
    images = posed_images(reconstruction)
    if len(images) < 1:
        return NoFloor("no registered image")
    up, prior_source = up_prior(reconstruction)
    max_tilt = opt.max_tilt_deg if prior_source == "camera x axes" else min(2.0 * opt.max_tilt_deg, 60.0)
    centres = np.array([im.projection_center() for im in images])
    lowest = float((centres @ up).min())

    ids, xyz, tracks = [], [], []
    frame_of = {image.image_id: name_of(image).frame for image in images}
    name_by_id = {image.image_id: image.name for image in images}
    for point_id, point in reconstruction.points3D.items():
        if point.track.length() >= opt.min_track_length and point.error <= opt.max_reprojection_error \
                and _simultaneous(point.track, frame_of):
            ids.append(point_id)
            xyz.append(point.xyz)
            tracks.append(point.track)
    ids = np.asarray(ids, dtype=np.int64)  # type: ignore[assignment]  # here an array
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)  # type: ignore[assignment]
    below = xyz @ up < lowest
    ids, xyz = ids[below], xyz[below]
    sparse_groups = [_rig_pair([name_by_id[e.image_id] for e in track.elements if e.image_id in name_by_id])
                     for track, keep in zip(tracks, below) if keep]
    markers = np.zeros((0, 3)) if markers is None else np.asarray(markers, dtype=np.float64).reshape(-1, 3)
    extra = np.zeros((0, 3)) if extra_points is None else np.asarray(extra_points, dtype=np.float64).reshape(-1, 3)
    extra_group = (["matched"] * len(extra) if extra_groups is None else
                   [_rig_pair(pair) for pair in extra_groups])
    if len(extra_group) != len(extra):
        raise ValueError(f"{len(extra_group)} extra_groups for {len(extra)} extra_points")
    extra_below = extra @ up < lowest
    extra = extra[extra_below]
    groups = np.array([*sparse_groups, *(g for g, keep in zip(extra_group, extra_below) if keep),
                       *["markers"] * len(markers)], dtype=object)
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
                        "are the markers on the floor? (or a and b swapped in one image: the bar then triangulates "
                        "off the floor at another length, and sets a wrong scale where it is the only measurement)")
    angle = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
    scatter_normal_sigma, scatter_height_sigma = plane_precision(points[inliers], normal, max(robust_sigma, rms / 3),
                                                                 centres)
    grouped = grouped_plane_precision(points[inliers], groups[inliers].astype(str), normal, offset, centres)
    if not np.isfinite(grouped["normal_sigma_deg"]):  # too few pairs to see their shared error: the scatter's
        grouped.update(normal_sigma_deg=scatter_normal_sigma, height_sigma=scatter_height_sigma,
                       height_sigmas=np.full(len(centres), scatter_height_sigma))
        sigma_basis = (f"the points' scatter alone, a lower bound: {grouped['num_groups']} image pair(s) cannot show "
                       "the pose error each pair's points share")
    elif grouped["num_groups"] < MIN_GROUPS:
        sigma_basis = (f"weakly determined: {grouped['num_groups']} image pairs (want {MIN_GROUPS}) for the pose error "
                       "each pair's points share")
    else:
        sigma_basis = f"{grouped['num_groups']} image pairs, each pair's points sharing its pose error"
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
        normal_sigma_deg=grouped["normal_sigma_deg"], height_sigma=grouped["height_sigma"],
        scatter_normal_sigma_deg=scatter_normal_sigma, scatter_height_sigma=scatter_height_sigma,
        group_sigma=grouped["group_sigma"], num_groups=grouped["num_groups"],
        effective_groups=grouped["effective_groups"], sigma_basis=sigma_basis,
        grouped_normal_sigma_deg=grouped["normal_sigma_deg"],
        camera_height_sigmas={im.name: float(h) for im, h in zip(images, grouped["height_sigmas"])},
    )


def marker_floor(reconstruction: pycolmap.Reconstruction, markers: np.ndarray, reason: str,
                 options: FloorOptions | None = None, *, x_towards: str | None = None) -> FloorFit | NoFloor:
    """The floor through the known-length markers alone, where no floor fits the points (``reason``: why; a dense
    crowd hides the floor from the sparse points and the floor matches). Markers lie on the floor (README), so:

    - end points spread over the floor (two bars apart: 4 or more points not on one line): their least-squares plane,
      its sigmas from their residuals over their n - 3 degrees of freedom, widened by Student's t;
    - on one line (one bar): the plane through that line nearest the cameras' up (their x axes, mounted without
      roll): the tilt about the bar is then the prior's error, estimated as the cameras' roll scatter over the
      square root of the rigs (measured: 0.18 deg said, 0.19 deg true on a rendered 6-rig crowd).

    A plane more than ``max_tilt_deg`` from the cameras' up, or with a camera below it, is no floor (markers on a
    wall, or mistaken image points)."""
    opt = options or FloorOptions()
    points = np.asarray(markers, dtype=np.float64).reshape(-1, 3)
    images = posed_images(reconstruction)
    if len(points) < 2 or not images:
        return NoFloor(reason)
    up, prior_source = up_prior(reconstruction)
    max_tilt = opt.max_tilt_deg if prior_source == "camera x axes" else min(2.0 * opt.max_tilt_deg, 60.0)
    centres = np.array([im.projection_center() for im in images])
    centroid = points.mean(axis=0)
    _, spread, axes = np.linalg.svd(points - centroid, full_matrices=False)
    x_axes = np.array([im.cam_from_world().rotation.matrix()[0] for im in images])
    rolls = np.degrees(np.arcsin(np.clip(x_axes @ up, -1.0, 1.0)))
    # per axis: each rig's roll tilts the up along one horizontal direction, so n rigs measure each axis about n/2
    # times, and the up fitted to them leaves n - 2 of their n degrees of freedom in the rolls' scatter; widened by
    # Student's t over 1.96 so that 1.96 sigmas hold 95 % with that few (4 rigs: 2 degrees of freedom)
    rigs = len(rig_positions(reconstruction))
    if rigs > 2:
        from scipy.stats import t as student_t

        widen = float(student_t.ppf(0.975, rigs - 2)) / 1.96
        prior_sigma = float(np.sqrt(np.mean(rolls**2) * 2.0 / (rigs - 2))) * widen
    else:
        prior_sigma = float("inf")  # two rigs' x axes fix the up exactly, whatever their rolls
    spread_out = len(points) >= 4 and spread[1] > 0.1 * spread[0]
    if spread_out:
        normal, offset = fit_plane(points)
        normal, offset = (normal, offset) if normal @ up >= 0 else (-normal, -offset)
        how = f"the {len(points)} known-length end points alone (bars apart on the floor fix its tilt)"
    elif not np.isfinite(prior_sigma):
        return NoFloor(f"{reason}; the known-length markers lie on one line, and two rigs cannot tell how the floor "
                       "tilts about it: put a second known length on the floor, away from the first (scale.yaml)")
    else:
        bar = axes[0]
        normal = up - (up @ bar) * bar
        normal /= np.linalg.norm(normal)
        offset = -float(normal @ centroid)
        how = ("the known-length bar's ends and the cameras' up (their x axes: cameras mounted without roll), so its "
               f"tilt about the bar is the cameras' mean roll, about {prior_sigma:.2g} deg here; for a measured floor "
               "put a second known length on the floor, away from the first (scale.yaml)")
    angle = float(np.degrees(np.arccos(np.clip(normal @ up, -1.0, 1.0))))
    heights = centres @ normal + offset
    if angle > max_tilt or heights.min() <= 0:
        return NoFloor(f"{reason}; the known-length markers' plane is {angle:.0f} deg from the cameras' up"
                       f"{' and has a camera below it' if heights.min() <= 0 else ''} (markers off the floor, or a bar's ends "
                       "a and b swapped in one image, which also sets a wrong scale where it is the only measurement)")
    residuals = points @ normal + offset
    rms = float(np.sqrt(np.mean(residuals**2)))
    if spread_out:
        # the residuals' sigma over their n - 3 degrees of freedom, widened by Student's t over 1.96: two bars' four
        # ends leave one, and their RMS alone often lies near 0
        dof = len(points) - 3
        from scipy.stats import t as student_t

        sigma = float(np.sqrt(np.sum(residuals**2) / dof)) * float(student_t.ppf(0.975, dof)) / 1.96
        normal_sigma, _ = plane_precision(points, normal, sigma, centres)
        height_sigmas = np.array([plane_precision(points, normal, sigma, c[None])[1] for c in centres])
        basis = (f"the {len(points)} known-length end points' residuals over their {dof} degree(s) of freedom, "
                 "widened by Student's t")
    else:  # the tilt about the bar, levered to each camera's distance from it
        across_bar = np.cross(normal, axes[0])
        normal_sigma = prior_sigma
        height_sigmas = np.radians(prior_sigma) * np.abs((centres - centroid) @ across_bar)
        basis = f"the cameras' rolls about their up ({rigs} rigs): the tilt about the one known-length bar"
    height_sigma = float(height_sigmas.max())
    floor_from_model, origin_rig = _floor_frame(normal, offset, reconstruction, x_towards)
    warning = f"no floor fits the points ({reason}): the floor is the plane of {how}"
    logger.info("floor: %s", warning)
    return FloorFit(
        normal=normal, offset=float(offset), rms=rms, robust_sigma=1.4826 * float(np.median(np.abs(residuals))),
        threshold=0.0, num_points=len(points), num_candidates=len(points),
        points_by_source={"sparse": 0, "matched": 0, "markers": len(points)},
        up_prior=up, up_prior_source=prior_source, prior_angle_deg=angle,
        floor_from_model=floor_from_model, origin_rig=origin_rig,
        camera_heights={im.name: float(h) for im, h in zip(images, heights)},
        marker_residuals=[float(v) for v in residuals], warnings=(warning,),
        normal_sigma_deg=float(normal_sigma), height_sigma=height_sigma,
        # the markers are too few to gate on their scatter: the same sigmas stand for it
        scatter_normal_sigma_deg=float(normal_sigma), scatter_height_sigma=height_sigma,
        grouped_normal_sigma_deg=float(normal_sigma), sigma_basis=basis,
        camera_height_sigmas={im.name: float(h) for im, h in zip(images, height_sigmas)},
    )
