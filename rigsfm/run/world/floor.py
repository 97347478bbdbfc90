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
   the plane give :class:`NoFloor` with the reason. Where markers were given, the floor is then theirs
   (:func:`rigsfm.run.world.floor_fit.marker_floor`: a crowd hides the floor from the points); else the caller
   warns and keeps the mapper's frame.
6. **Cost.** :func:`estimate_floor` reads images only when the sparse points and markers do not fix the floor
   (:func:`sparse_floor_shortfall`: fewer than 100 inliers, or standard errors of the normal above 0.02 deg or of
   a camera height above 0.2 % of it). Then floor matching (:mod:`rigsfm.run.world.floor_matching`) triangulates
   floor points between each wide image and those of its 4 nearest rigs, and stops as soon as the fit is
   precise enough. Fewer neighbours tilt the floor (each pair's points lie in one region, offset by that pair's
   pose errors: more pairs average them), more cost time for no gain (see benchmarks/README.md).

The frame: z = the plane's upward normal; origin = the orthogonal projection onto the plane of the centroid of
the rig positions (a rig's position = its reference (wide) camera centre, averaged over its registered
frames); x axis = horizontal direction from the origin towards the first rig (lowest rig id, i.e. the first
rig of rigs.yaml, or the rig named by ``x_towards``); y = z x x (right-handed). If the first rig stands over the
origin (a single rig), x follows its wide camera's viewing direction projected on the floor.

``FloorFit.floor_from_model`` is a ``pycolmap.Rigid3d``; apply it with :func:`apply_floor_frame`, which calls
``Reconstruction.transform`` with a scale-1 ``Sim3d``. COLMAP's ``Reconstruction::Transform`` multiplies every
non-reference ``sensor_from_rig`` translation by the similarity's scale, so scale 1 leaves E^sl untouched (a
metric model must never be re-scaled here: the metres come from ``rigsfm.run.adjustment``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from rigsfm.core.summary import floor_from_markers_alone
from rigsfm.run.world.floor_fit import fit_floor, marker_floor
from rigsfm.run.world.floor_model import (
    FloorFit,
    FloorOptions,
    NoFloor,
    posed_images,
    up_prior,
)

if TYPE_CHECKING:  # floor matching imports OpenCV: only where the floor is matched
    from rigsfm.run.adjustment.result import JointCovariance
    from rigsfm.run.world.floor_matching import FloorMatches

logger = logging.getLogger(__name__)

LOWEST_POINTS = "lowest sparse points and the cameras' up"  # guess_floor's guess from the sparse points' heights
LOWER_STEPS = (0.1, 0.2, 0.3, 0.4)  # that guess lowered by these fractions of the camera height above it


def apply_floor_frame(reconstruction: pycolmap.Reconstruction, fit: FloorFit) -> None:
    """Move ``reconstruction`` into the floor frame in place (scale 1: ``sensor_from_rig`` is unchanged)."""
    transform = fit.floor_from_model
    reconstruction.transform(pycolmap.Sim3d(1.0, transform.rotation, transform.translation))


def axes_convergence(reconstruction: pycolmap.Reconstruction) -> np.ndarray | None:
    """The point closest (least squares) to every registered camera's optical axis, or None when the axes do
    not converge in front of every camera. Crowd rigs aim at the floor, so this is a point near it."""
    images = posed_images(reconstruction)
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
                options: FloorOptions | None = None, sparse: FloorFit | NoFloor | None = None
                ) -> tuple[np.ndarray, float, str] | NoFloor:
    """A rough floor plane (normal, offset, how) to warp images with, in order of preference: a floor fitted
    to the sparse points; the up prior through the markers' mean height; the up prior through the 2nd
    percentile of the heights of the sparse points below the cameras (the floor is the lowest large surface);
    the up prior through the point where the cameras' optical axes converge, if it lies below every camera.
    ``sparse``: that fit where the caller made it already (a failed fit draws every RANSAC triple: seconds)."""
    fit = fit_floor(reconstruction, markers, options, quiet=True) if sparse is None else sparse
    if fit:
        return fit.normal, fit.offset, "sparse points"  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
    up, _ = up_prior(reconstruction)
    if markers is not None and len(markers):
        return up, -float(np.mean(np.asarray(markers).reshape(-1, 3) @ up)), "markers and the cameras' up"
    lowest = float(min(im.projection_center() @ up for im in posed_images(reconstruction)))
    heights = np.array([p.xyz for p in reconstruction.points3D.values()]).reshape(-1, 3) @ up
    heights = heights[heights < lowest]
    if len(heights) >= (options or FloorOptions()).min_points:
        return up, -float(np.percentile(heights, 2.0)), LOWEST_POINTS
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
    matches: FloorMatches | None = None  # the last round's matches (their pixels: refit_floor triangulates them again)
    refitted: bool = False  # fitted again on the model adjusted once more (refit_floor)


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
    if fit.scatter_normal_sigma_deg > opt.enough_normal_sigma_deg:  # type: ignore[union-attr]
        return (f"their normal is uncertain by {fit.scatter_normal_sigma_deg:.3f} deg from their scatter (want "  # type: ignore[union-attr]
                f"{opt.enough_normal_sigma_deg})")
    if fit.scatter_height_sigma > opt.enough_height_sigma * median_height:  # type: ignore[union-attr]
        return (f"camera heights uncertain by {fit.scatter_height_sigma:.3g} from their scatter (want "  # type: ignore[union-attr]
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
    the floor; the second round through the fit 679 and 391). Where the guess came from the lowest sparse points
    and no floor fits, the guess is lowered by each of ``LOWER_STEPS`` and the rounds start again from the step
    that matched the most points with a floor fitted to them."""
    import time

    from rigsfm.run.world.floor_matching import load_floor_images, match_floor_points

    opt = options or FloorOptions()
    sparse = fit_floor(reconstruction, markers, opt, x_towards=x_towards, quiet=True)
    shortfall = sparse_floor_shortfall(sparse, reconstruction, opt)
    if shortfall is None or image_dir is None:
        if not sparse and markers is not None and len(markers):
            sparse = marker_floor(reconstruction, markers, sparse.reason, opt, x_towards=x_towards)  # type: ignore[union-attr]  # FloorFit is truthy: a NoFloor here
        # NoFloor is falsy: a FloorFit here
        for warning in sparse.warnings if sparse else ():  # type: ignore[union-attr]
            logger.warning("floor: %s", warning)
        return FloorEstimate(sparse, why_matched=None)
    logger.info("floor: matching the floor between images (%s)", shortfall)
    start = time.perf_counter()
    # NoFloor is falsy: a FloorFit here
    guess = (sparse.normal, sparse.offset, "sparse points") if sparse else guess_floor(reconstruction, markers, opt,  # type: ignore[union-attr]
                                                                                       sparse)
    if not guess:
        return FloorEstimate(guess, shortfall, seconds=time.perf_counter() - start)
    normal, offset, how = guess  # type: ignore[misc]  # NoFloor is falsy: a tuple here
    logger.info("floor guess from the %s", how)
    centres = np.array([im.projection_center() for im in posed_images(reconstruction)])
    images = load_floor_images(reconstruction, image_dir, match_options, up=normal)

    def rounds_from(normal: np.ndarray, offset: float, matched=None) -> tuple[FloorFit | NoFloor, int, int, int]:
        """Match, fit, and match again through the fit while it moved (fit, rounds, image pairs, matches);
        ``matched``: the first round's matches and their fit where they were made already (not counted again)."""
        fit: FloorFit | NoFloor = NoFloor("no matching round ran")
        rounds = pairs = found = 0
        for _ in range(max(1, max_rounds)):
            if matched is not None:
                (matches, fit), matched = matched, None
            else:
                matches = match_floor_points(reconstruction, image_dir, normal, offset, match_options, images=images)
                rounds, pairs = rounds + 1, pairs + len(matches.pairs)
                fit = fit_floor(reconstruction, markers, opt, extra_points=matches.points,
                                extra_groups=matches.groups(), x_towards=x_towards, quiet=True)
            found, last[0] = len(matches), matches
            if not fit or sparse_floor_shortfall(fit, reconstruction, opt) is None:
                break  # no floor, or precise enough
            # NoFloor is falsy: a FloorFit here
            moved_deg = float(np.degrees(np.arccos(np.clip(fit.normal @ normal, -1.0, 1.0))))  # type: ignore[union-attr]
            moved = float(np.max(np.abs(fit.height(centres) - (centres @ normal + offset))))  # type: ignore[union-attr]
            if moved_deg <= 0.05 and moved <= 0.005 * float(np.median(fit.height(centres))):  # type: ignore[union-attr]
                break
            logger.info("floor moved by %.3f deg / %.3g at the cameras from the matching plane", moved_deg, moved)
            normal, offset = fit.normal, fit.offset  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
        return fit, rounds, pairs, found

    last: list = [None]  # the matches of the last fit made

    fit, rounds, pairs, found = rounds_from(normal, offset)
    if not fit and how == LOWEST_POINTS:
        # A crowd (or any clutter) covering the floor leaves its lowest sparse points on bodies and boxes above it,
        # and a warp through a plane that high matches little: the plane lowered step by step, the one matching
        # the most floor points (with a floor fitted to them) is where the rounds start again.
        height = float(np.median(centres @ normal + offset))
        best = None  # (its matches, their fit, the lowered offset)
        for step in LOWER_STEPS:
            lowered = offset + step * height
            matches = match_floor_points(reconstruction, image_dir, normal, lowered, match_options, images=images)
            pairs += len(matches.pairs)
            if best is not None and len(matches) <= len(best[0]):
                continue  # it cannot be chosen, whatever its fit (a failed fit draws every RANSAC triple: seconds)
            step_fit = fit_floor(reconstruction, markers, opt, extra_points=matches.points,
                                 extra_groups=matches.groups(), x_towards=x_towards, quiet=True)
            if step_fit:
                best = (matches, step_fit, lowered)
        logger.info("floor guess lowered: %s", "no step fits a floor" if best is None else
                    f"{(best[2] - offset) / height:.0%} of the camera height matched the most ({len(best[0])} points)")
        if best is not None:  # its matches and fit are the rounds' first: matched and fitted once
            lowered_fit, more_rounds, more_pairs, found = rounds_from(normal, best[2], best[:2])
            fit, rounds, pairs = lowered_fit, rounds + len(LOWER_STEPS) + more_rounds, pairs + more_pairs
    if not fit and sparse:
        fit, last[0] = sparse, None  # the matches did not help: keep the sparse floor
    if not fit and markers is not None and len(markers):  # a crowd hides the floor: its markers are floor points
        fit, last[0] = marker_floor(reconstruction, markers, fit.reason, opt, x_towards=x_towards), None  # type: ignore[union-attr]  # FloorFit is truthy: a NoFloor here
    for warning in fit.warnings if fit else ():  # type: ignore[union-attr]  # NoFloor is falsy: a FloorFit here
        logger.warning("floor: %s", warning)
    seconds = time.perf_counter() - start
    logger.info("floor matching: %d round(s), %d image pairs, %.1f s", rounds, pairs, seconds)
    return FloorEstimate(fit, shortfall, rounds, pairs, found, seconds, last[0] if fit else None)


def refit_floor(estimate: FloorEstimate, reconstruction: pycolmap.Reconstruction, markers: np.ndarray | None = None,
                options: FloorOptions | None = None, *, x_towards: str | None = None) -> FloorEstimate:
    """``estimate``'s floor fitted again in ``reconstruction``, the same model adjusted once more (the narrow stage's
    second adjustment moves the network: the first fit, carried over, was off the delivered poses by up to 36 mm,
    benchmarks/README.md): its sparse points, ``markers`` and the floor matches' pixels triangulated with the new
    poses; no image is read again. The estimate unchanged where it has no floor, or no floor fits again."""
    if not estimate.fit:
        return estimate
    before: FloorFit = estimate.fit  # type: ignore[assignment]  # NoFloor is falsy: a FloorFit here
    if floor_from_markers_alone(before.points_by_source, before.num_points) and markers is not None and len(markers):
        # the markers again, in the new poses
        fit = marker_floor(reconstruction, markers, "no floor fitted the points", options, x_towards=x_towards)
    else:
        matches = estimate.matches
        points, groups = matches.triangulated_in(reconstruction) if matches is not None else (None, None)
        fit = fit_floor(reconstruction, markers, options, extra_points=points, extra_groups=groups,
                        x_towards=x_towards, quiet=True)
    if not fit:
        # FloorFit is truthy: a NoFloor here
        logger.warning("floor: not found again after the narrow adjustment (%s); the first fit is kept",
                       fit.reason)  # type: ignore[union-attr]
        return estimate
    return replace(estimate, fit=fit, refitted=True)


def with_pose_uncertainty(estimate: FloorEstimate, reconstruction: pycolmap.Reconstruction,
                          covariance: JointCovariance | None) -> FloorEstimate:
    """``estimate`` with its normal's sigma widened to the poses' share where that is larger than the pairs'
    residuals show: the poses' covariance carried through the floor points' triangulation (the floor matches and
    the sparse floor points, :func:`rigsfm.run.world.floor_poses.pose_floor_covariance`) and the points' scatter, in
    quadrature. A network's pose errors are correlated from pair to pair, so the plane can be off with every pair
    agreeing (benchmarks/README.md): a floor of sparse points alone as much as a matched one. Each camera's height
    sigma from the same poses, the camera and the floor moved together, is kept beside it
    (``pose_camera_height_sigmas``, :meth:`rigsfm.run.world.frame.WorldResult.set_narrow_heights`). Unchanged without
    floor points (a floor of markers alone) or a covariance. ``reconstruction``: the model the fit is in (before
    the floor frame is applied)."""
    if not estimate.fit or covariance is None:
        return estimate
    fit: FloorFit = estimate.fit  # type: ignore[assignment]  # NoFloor is falsy: a FloorFit here
    if estimate.matches is None and not len(fit.inlier_ids):
        return estimate
    from rigsfm.run.world.floor_poses import pose_floor_covariance

    found = pose_floor_covariance(reconstruction, estimate.matches, fit.normal, fit.offset, fit.threshold, covariance,
                                  sparse_ids=fit.inlier_ids)
    if found is None:
        return estimate
    tilt, heights = found
    pose_sigma = float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(tilt).max()), 0.0))))
    from_poses = float(np.hypot(pose_sigma, fit.scatter_normal_sigma_deg))
    normal_sigma = max(fit.normal_sigma_deg, from_poses)
    basis = fit.sigma_basis + ("; widened to the poses' covariance carried through the floor points"
                               if from_poses > fit.normal_sigma_deg else "")
    return replace(estimate, fit=replace(fit, normal_sigma_deg=normal_sigma, pose_normal_sigma_deg=pose_sigma,
                                         sigma_basis=basis, pose_camera_height_sigmas=heights))
