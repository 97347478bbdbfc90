"""What the result is worth: the joint covariance of rig poses and calibration, each narrow camera's uncertainty,
and the 95 % epipolar band of every narrow pair.

1. :func:`joint_covariance`: the covariance of every rig pose, E^sl and camera (3D points marginalised out). Ceres'
   Jacobian of the adjustment's own problem (``rigsfm.run.adjustment.adjust.JointProblem``, squared loss: the inliers'
   covariance; ``Problem.evaluate_jacobian``, tangent space), the points eliminated by a Schur complement of their
   3x3 blocks, the rest inverted densely, times the images' weighting noise squared (every residual is in pixels).
   COLMAP's ``estimate_ba_covariance`` is not used: it gives a non-pose block only on its own, without its
   cross-covariance with the poses, which the band needs (an E^sl error and a rig pose error partly cancel).
   - ``REFINE``: the posterior of the adjustment with calibration priors.
   - ``FIXED``: the calibration was held, so the images did not improve it: the poses' image noise plus the
     calibration prior pushed through the estimate's sensitivity to it ("consider parameters": with the reduced
     normal matrix ``[[A, B], [B^T, C]]`` over poses and calibration, ``S = -A^-1 B``, ``Cov(poses) =
     sigma^2 A^-1 + S Sigma_c S^T``, ``Cov(poses, calibration) = S Sigma_c``, ``Cov(calibration) = Sigma_c``).
   Tangents: ``("frame", frame_id)``: ``rig_from_world``, ``("sensor_from_rig", camera_id)``: a narrow camera's
   E^sl, both ``[w, dt]`` with ``R' = Exp(w) R``, ``t' = t + dt`` (rad, m); ``("camera", camera_id)``: the params.
   A parameter no image observes keeps its prior, independent of the rest (``prior_only``).
2. :func:`narrow_uncertainty`: per narrow camera the 1-sigma uncertainty of its centre (mm) and of its rotation
   (deg), each the root of the trace of its 3x3 covariance (the RMS length of the 3D error), relative to the
   network as a whole: the covariance is transformed to the datum in which the registered rigs' mean centre and
   mean orientation are held (an S-transformation), so no rig is special.
3. :func:`narrow_pair_bands`: the band an analyst can search. A pixel ``x_i`` of narrow image i is clicked, its
   epipolar line drawn in j with the *estimated* cameras and pose (pinhole pixels of j, the frame of ``F_ji``),
   and the correspondence ``x_j`` sought near it. Under a possible truth (a draw from the joint covariance), the
   scene point is on the drawn ray of ``x_i`` at the analysis point's depth, ``x_j`` is its projection with the
   drawn camera j, and ``d`` its distance from the estimated line. The draws' effect on ``d`` is linear to far
   below a pixel (errors of 0.1 deg and a few pixels), so ``d = J z``: ``J`` (points x parameters) comes from
   the chain rule on the poses and from finite differences through pycolmap's camera models (any model, no
   camera object per draw), and ``z`` from the covariance. The analysis points are points of the floor (through
   scale.yaml's known lengths, else the sparse points' dominant horizontal plane) seen by both narrow cameras on a
   15 x 15 grid of image i; without a floor in the shared view, the grid at every depth at which it appears in
   image j (0.1x to 100x the pair's distance, uniform in inverse depth). The band half-width is the 95 % quantile
   of ``|d|`` pooled over the analysis points and the covariance (exact for the linear model: it solves
   ``mean_p P(|d_p| <= b) = 0.95``). It is calibrated, not a bound: a true correspondence of a floor point lies
   inside it with 95 % probability, pooled over points and over the calibration's possible errors. The
   calibration error is one draw per pair, so the share of points inside the band *for one pair* varies from
   pair to pair: ``PairBand.predicted_coverage`` is its predicted distribution (one value per draw), and
   ``predicted_below_85`` the predicted probability that fewer than 85 % of a pair's points lie inside.
   Pairs whose images share no view get no band.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyceres
import pycolmap
import scipy.linalg
import scipy.sparse as sp
from scipy.special import ndtr

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.geometry import project, project_world
from rigsfm.core.names import name_of
from rigsfm.run.adjustment.adjust import (
    AdjustResult,
    Gauge,
    JointProblem,
    ScaleSource,
    estimate_pixel_sigma,
    sensor_from_rig_view,
)
from rigsfm.run.adjustment.priors import calibration_priors, draw_calibration
from rigsfm.run.options import Calibration

logger = logging.getLogger(__name__)

BAND_PROBABILITY = 0.95
PAIR_COVERAGE_LEVEL = 0.85  # the per-pair coverage whose predicted shortfall is reported
DAMPING = 1e-8  # added to each point's 3x3 block in the Schur complement
RANK_TOLERANCE = 1e-10  # smallest / largest eigenvalue of the Jacobi-scaled reduced normal matrix


# ------------------------------------------------------------------------------------------------------------
# 1. The joint covariance


@dataclass(frozen=True)
class JointCovariance:
    """Joint covariance of rig poses and calibration, points marginalised out (module docstring, 1.).
    Held parameters (the gauge, sigma-0 intrinsics) have zero rows."""

    keys: tuple[tuple[str, int], ...]
    offsets: dict
    covariance: np.ndarray
    pixel_sigma: float  # the images' weighting noise (estimated noise x AdjustOptions.pixel_sigma_inflation)
    kind: str  # "posterior" (REFINE) or "consider" (FIXED)
    prior_only: frozenset = frozenset()
    seconds: float = 0.0

    def slice(self, key) -> slice:
        start, size = self.offsets[key]
        return slice(start, start + size)

    def index(self, keys: Sequence) -> np.ndarray:
        return np.concatenate([np.arange(self.offsets[k][0], sum(self.offsets[k])) for k in keys])

    def sub(self, keys: Sequence) -> np.ndarray:
        index = self.index(keys)
        return self.covariance[np.ix_(index, index)]

    def sigma(self, key) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance[self.slice(key), self.slice(key)]), 0.0, None))


def _csr(jacobian: pyceres.CRSMatrix) -> sp.csr_matrix:
    return sp.csr_matrix((np.asarray(jacobian.values), np.asarray(jacobian.cols), np.asarray(jacobian.rows)),
                         shape=(jacobian.num_rows, jacobian.num_cols))


def _reduced_system(jp: JointProblem):
    """Ceres' Jacobian of ``jp`` (tangent space) with the points eliminated (Schur complement, 3x3 blocks): the
    reduced normal matrix over the other blocks, every entry ``(key, block or None, size, tangent dims)``, the
    variable ones, and the prior-only covariances; None (with a warning) when a point carries no information."""
    rec, problem = jp.reconstruction, jp.problem
    entries: list[tuple[tuple, Any, int, Any]] = []  # (key, block or None, size, dims or None)
    for frame_id in jp.frame_ids:
        block = jp.frame_block(frame_id)
        if not jp.has_variable(block):
            entries.append((("frame", frame_id), None, 6, None))
            continue
        dims = list(range(6))
        if jp.subset_frame is not None and jp.subset_frame[0] == frame_id:
            dims.remove(3 + jp.subset_frame[1])
        entries.append((("frame", frame_id), block, 6, dims))
    prior_only = {}
    for rig_id, sensor_id, camera_id, rig_name in jp.narrow_sensors():
        view = sensor_from_rig_view(rec, rig_id, sensor_id)
        key = ("sensor_from_rig", camera_id)
        if jp.has_variable(view.params):
            entries.append((key, view.params, 6, list(range(6))))
        else:
            prior_only[key] = jp.priors[rig_name].narrow_from_wide
            entries.append((key, None, 6, None))
    for camera_id in sorted(rec.cameras):
        if camera_id not in jp.camera_names:
            continue
        camera = rec.cameras[camera_id]
        key, sigmas = ("camera", camera_id), jp.camera_sigmas(camera_id)
        if jp.has_variable(camera.params):
            entries.append((key, camera.params, len(sigmas), np.flatnonzero(sigmas > 0).tolist()))
        else:
            prior_only[key] = np.diag(sigmas**2)
            entries.append((key, None, len(sigmas), None))
    variable = [entry for entry in entries if entry[1] is not None]
    end_points = [p for p in jp.end_points if jp.has_variable(p)]
    points = [p.xyz for p in rec.points3D.values() if jp.has_variable(p.xyz)]
    blocks = [block for _, block, _, _ in variable] + end_points + points
    for key, block, _, dims in variable:
        if problem.parameter_block_tangent_size(block) != len(dims):
            raise RuntimeError(f"unexpected tangent size of {key}")
    evaluate = pyceres.EvaluateOptions()
    evaluate.set_parameter_blocks(blocks)
    jac = _csr(problem.evaluate_jacobian(evaluate)).tocsc()
    num_a = sum(len(dims) for _, _, _, dims in variable) + 3 * len(end_points)
    j_a, j_p = jac[:, :num_a], jac[:, num_a:]
    h_aa = (j_a.T @ j_a).toarray()
    if j_p.shape[1]:
        h_pp = (j_p.T @ j_p).tobsr(blocksize=(3, 3))
        num_points = j_p.shape[1] // 3
        if not (np.array_equal(h_pp.indices, np.arange(num_points))
                and np.array_equal(h_pp.indptr, np.arange(num_points + 1))):
            logger.warning("No joint covariance: some 3D points carry no information (every observation of them is "
                           "degenerate or cannot be projected)")
            return None
        inverse = np.linalg.inv(h_pp.data + DAMPING * np.eye(3))
        h_pp_inv = sp.bsr_matrix((inverse, np.arange(num_points), np.arange(num_points + 1)), shape=h_pp.shape)
        h_ap = (j_a.T @ j_p).tocsr()
        schur = h_aa - (h_ap @ h_pp_inv @ h_ap.T).toarray()
    else:
        schur = h_aa
    return 0.5 * (schur + schur.T), entries, variable, prior_only


def _inverse(matrix: np.ndarray) -> np.ndarray | None:
    """Inverse of a symmetric positive definite matrix with Jacobi scaling (radians, metres, pixels and
    distortion units differ by orders of magnitude), by Cholesky; None when rank deficient (a pivot below
    ``RANK_TOLERANCE`` of the largest)."""
    if matrix.size == 0:
        return matrix.copy()
    scaling = 1.0 / np.sqrt(np.clip(np.diag(matrix), 1e-300, None))
    scaled = matrix * np.outer(scaling, scaling)
    try:
        factor = np.linalg.cholesky(scaled)
    except np.linalg.LinAlgError:
        factor = None
    pivots = np.diag(factor) ** 2 if factor is not None else np.zeros(1)
    if factor is None or pivots.min() <= RANK_TOLERANCE * pivots.max():
        logger.warning("No joint covariance: the problem is rank deficient (smallest Cholesky pivot %.3g of %.3g)",
                       pivots.min(), pivots.max())
        return None
    inverse_factor = scipy.linalg.solve_triangular(factor, np.eye(len(factor)), lower=True)
    return (inverse_factor.T @ inverse_factor) * np.outer(scaling, scaling)


def _tangent_factors(variable) -> np.ndarray:
    """Per variable tangent dimension: ours / Ceres' (``w = 2 delta`` for quaternion tangents, else 1)."""
    return np.concatenate([[2.0 if key[0] in ("frame", "sensor_from_rig") and d < 3 else 1.0 for d in dims]
                           # the empty case
                           for key, _, _, dims in variable] or [np.zeros(0)])  # type: ignore[list-item]


def _assemble(entries, variable, cov_a: np.ndarray, prior_only: dict) -> tuple:
    """Full covariance in our tangents (held rows zero) from the covariance over the variable dimensions
    (already in our tangents; the end points' trailing rows are dropped)."""
    offsets, start = {}, 0
    for key, _, size, _ in entries:
        offsets[key] = (start, size)
        start += size
    full = np.zeros((start, start))
    # the empty case
    target = np.concatenate([[offsets[key][0] + d for d in dims] for key, _, _, dims in variable] or [np.zeros(0)])  # type: ignore[list-item]
    target = target.astype(int)
    full[np.ix_(target, target)] = cov_a[: len(target), : len(target)]
    for key, cov in prior_only.items():
        s = slice(offsets[key][0], sum(offsets[key]))
        full[s, s] = cov
    return tuple(key for key, _, _, _ in entries), offsets, full


def joint_covariance(result: AdjustResult, image_only: bool = False) -> JointCovariance | None:
    """The joint covariance of ``result`` (not modified): the posterior for ``REFINE``, the consider covariance
    for ``FIXED`` (module docstring); with ``image_only`` the image noise's part alone (the consider covariance
    of a calibration known exactly); None when the problem is rank deficient (a warning says why)."""
    start = time.perf_counter()
    rec = pycolmap.Reconstruction(result.reconstruction)
    rigs = result.rigs
    priors = result.priors or calibration_priors(rigs)
    options = result.options
    pixel_sigma = result.pixel_sigma or estimate_pixel_sigma(rec, options.max_reprojection_error_px)
    gauge = Gauge.TWO_CAMS_FROM_WORLD if result.scale_source == ScaleSource.NONE else Gauge.RIGID
    refined = result.calibration == Calibration.REFINE and not image_only
    held = result.held_rigs if refined else frozenset()
    jp = JointProblem(rec, rigs, priors, result.scale_spec, options, pixel_sigma, gauge=gauge, robust=False,
                      with_priors=refined, held_rigs=held, consider_held=True)
    reduced = _reduced_system(jp)
    if reduced is None:
        return None
    schur, entries, variable, prior_only = reduced
    factors = _tangent_factors(variable)
    num_end = schur.shape[0] - len(factors)
    factors = np.r_[factors, np.ones(num_end)]
    if refined and held:  # the refined rigs' posterior, the held rigs' calibration considered
        cov = _consider(jp, schur, variable, factors, consider_rigs=held)
        if cov is None:
            return None
        kind = "posterior"
    elif refined:
        inverse = _inverse(schur)
        if inverse is None:
            return None
        cov = inverse * jp.weight_sigma**2 * np.outer(factors, factors)
        kind = "posterior"
    else:
        cov = _consider(jp, schur, variable, factors, 0.0 if image_only else 1.0)
        if cov is None:
            return None
        kind = "image" if image_only else "consider"
    if image_only:
        prior_only = {key: np.zeros_like(value) for key, value in prior_only.items()}
    keys, offsets, full = _assemble(entries, variable, cov, prior_only)
    return JointCovariance(keys, offsets, full, jp.weight_sigma, kind, frozenset(prior_only),
                           time.perf_counter() - start)


def _consider(jp: JointProblem, schur: np.ndarray, variable, factors: np.ndarray,
              prior_weight: float = 1.0, consider_rigs: frozenset[str] | None = None) -> np.ndarray | None:
    """The consider covariance (our tangents) over the variable dimensions, end points last. ``consider_rigs``:
    only these rigs' calibration is considered, the others' is estimated with the poses (their priors in
    ``schur``); None: every rig's is considered."""
    pose_index: list[int] = []
    calibration_index: list[int] = []
    prior_blocks: list = []
    k = 0
    for key, _, _, dims in variable:
        if key[0] == "frame" or (consider_rigs is not None and jp.camera_names[key[1]].rig not in consider_rigs):
            pose_index.extend(range(k, k + len(dims)))
        else:
            if key[0] == "camera":
                block = np.diag(jp.camera_sigmas(key[1]) ** 2)
            else:
                block = jp.priors[jp.camera_names[key[1]].rig].narrow_from_wide
            prior_blocks.append(block[np.ix_(dims, dims)])
            calibration_index.extend(range(k, k + len(dims)))
        k += len(dims)
    pose_index += list(range(k, schur.shape[0]))  # the known lengths' end points go with the poses
    # Everything in our tangents: the normal matrix scales with 1 / factor.
    scaled = schur / np.outer(factors, factors)
    a = scaled[np.ix_(pose_index, pose_index)]
    b = scaled[np.ix_(pose_index, calibration_index)]
    a_inv = _inverse(a)
    if a_inv is None:
        return None
    prior = np.zeros((len(calibration_index), len(calibration_index)))
    at = 0
    for block in prior_blocks:
        prior[at:at + len(block), at:at + len(block)] = block
        at += len(block)
    prior *= prior_weight
    sensitivity = -a_inv @ b
    cov = np.zeros_like(schur)
    cov[np.ix_(pose_index, pose_index)] = a_inv * jp.weight_sigma**2 + sensitivity @ prior @ sensitivity.T
    cov[np.ix_(pose_index, calibration_index)] = sensitivity @ prior
    cov[np.ix_(calibration_index, pose_index)] = (sensitivity @ prior).T
    cov[np.ix_(calibration_index, calibration_index)] = prior
    return cov


def _frame_centre_jacobian(rigid: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``-R^T t`` of a pose and its Jacobian (3x6) with respect to ``[w, dt]``."""
    r, t = rigid.rotation.matrix(), np.asarray(rigid.translation)
    return -r.T @ t, np.hstack([-r.T @ _skew(t), -r.T])


def network_size_sigma(covariance: JointCovariance | None, reconstruction: pycolmap.Reconstruction) -> float | None:
    """Relative 1-sigma uncertainty of the distance between the two registered frames farthest apart: how well
    the network's size (its metric scale) is known."""
    if covariance is None:
        return None
    frames = sorted(reconstruction.reg_frame_ids())
    # registered frames have their poses
    centres = {f: _frame_centre_jacobian(reconstruction.frame(f).rig_from_world) for f in frames}  # type: ignore[arg-type]
    best, pair = 0.0, None
    for k, a in enumerate(frames):
        for b in frames[k + 1:]:
            d = float(np.linalg.norm(centres[a][0] - centres[b][0]))
            if d > best:
                best, pair = d, (a, b)
    if pair is None or best <= 0:
        return None
    a, b = pair
    u = (centres[a][0] - centres[b][0]) / best
    jac = np.hstack([u @ centres[a][1], -u @ centres[b][1]])
    cov = covariance.sub([("frame", a), ("frame", b)])
    return float(np.sqrt(max(jac @ cov @ jac, 0.0))) / best


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# ------------------------------------------------------------------------------------------------------------
# 2. Each narrow camera


@dataclass(frozen=True)
class NarrowUncertainty:
    centre_sigma_mm: float  # sqrt(trace) of the centre's 3x3 covariance, relative to the network (mm)
    rotation_sigma_deg: float  # sqrt(trace) of the orientation's 3x3 covariance, relative to the network (deg)


def _narrow_images(reconstruction: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted((im for im in reconstruction.images.values() if im.has_pose and name_of(im).is_narrow),
                  key=lambda im: im.name)


def _world_jacobian(pose: pycolmap.Rigid3d) -> np.ndarray:
    """``[delta theta (world-frame orientation), delta centre]`` (6) from a pose's ``[w, dt]`` (6)."""
    r, t = pose.rotation.matrix(), np.asarray(pose.translation)
    return np.block([[-r.T, np.zeros((3, 3))], [-r.T @ _skew(t), -r.T]])


def narrow_tangent_jacobians(frame_pose: pycolmap.Rigid3d, sensor: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """``[w, dt]`` of ``narrow_from_world = E * rig_from_world`` from ``[w, dt]`` of the frame and of E (6x6 each)."""
    r_e = sensor.rotation.matrix()
    d_frame = np.block([[r_e, np.zeros((3, 3))], [np.zeros((3, 3)), r_e]])
    d_sensor = np.eye(6)
    d_sensor[3:, :3] = -_skew(r_e @ np.asarray(frame_pose.translation))
    return d_frame, d_sensor


def narrow_uncertainty(reconstruction: pycolmap.Reconstruction,
                       covariance: JointCovariance) -> dict[str, NarrowUncertainty]:
    """Per narrow image (module docstring, 2.): centre and rotation uncertainty relative to the network."""
    frames = sorted(f for f in reconstruction.reg_frame_ids() if ("frame", f) in covariance.offsets)
    if not frames:
        return {}
    size = covariance.covariance.shape[0]
    # registered frames have their poses
    centres = {f: _frame_centre_jacobian(reconstruction.frame(f).rig_from_world)[0] for f in frames}  # type: ignore[arg-type]
    mean_centre = np.mean(list(centres.values()), axis=0)
    datum = np.zeros((6, size))  # mean [delta theta, delta centre] of the frames: the gauge motion to remove
    for f in frames:
        # registered frames have their poses
        datum[:, covariance.slice(("frame", f))] += _world_jacobian(reconstruction.frame(f).rig_from_world) / len(frames)  # type: ignore[arg-type]
    out = {}
    for image in _narrow_images(reconstruction):
        frame = reconstruction.frame(image.frame_id)
        sensor = sensor_from_rig_view(reconstruction, frame.rig_id, reconstruction.cameras[image.camera_id].sensor_id)
        pose = image.cam_from_world()
        # registered frames have their poses
        d_frame, d_sensor = narrow_tangent_jacobians(frame.rig_from_world, sensor)  # type: ignore[arg-type]
        world = _world_jacobian(pose)
        row = np.zeros((6, size))
        row[:, covariance.slice(("frame", image.frame_id))] = world @ d_frame
        key = ("sensor_from_rig", image.camera_id)
        if key in covariance.offsets:
            row[:, covariance.slice(key)] = world @ d_sensor
        correction = np.eye(6)
        correction[3:, :3] = -_skew(pose.inverse().translation - mean_centre)  # the gauge rotation moves the centre
        row -= correction @ datum
        cov = row @ covariance.covariance @ row.T
        out[image.name] = NarrowUncertainty(
            centre_sigma_mm=1000.0 * float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))),
            rotation_sigma_deg=float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))))
    return out


# ------------------------------------------------------------------------------------------------------------
# 3. Analysis points: the floor


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
    from rigsfm.run.adjustment.scale import triangulate_observed_point

    ends = []
    for item in (scale_spec.known_lengths if scale_spec is not None else ()):
        for end in ("a", "b"):
            point = triangulate_observed_point(reconstruction, [(o.image, np.asarray(getattr(o, end)))
                                                                for o in item.observations])
            if point is not None:
                ends.append(point)
    if not ends:
        return None
    up = world_up(reconstruction)
    return Plane(up, -float(up @ np.mean(ends, axis=0)), len(ends))


def find_floor(reconstruction: pycolmap.Reconstruction, scale_spec=None) -> tuple[Plane | None, str]:
    """The floor through the known lengths, else from the sparse points when a tenth of them lie on it;
    ``(None, "none")`` without either. The second value says which (``known_lengths``, ``points``)."""
    plane = floor_from_known_lengths(reconstruction, scale_spec)
    if plane is not None:
        return plane, "known_lengths"
    plane = ground_plane(reconstruction, min_points=max(30, reconstruction.num_points3D() // 10))
    return (plane, "points") if plane is not None else (None, "none")


def grid_pixels(camera: pycolmap.Camera, n: int = 15) -> np.ndarray:
    """Centres of an n x n grid of cells over the image (COLMAP pixels)."""
    u = (np.arange(n) + 0.5) / n
    return np.array([(x * camera.width, y * camera.height) for y in u for x in u], dtype=np.float64)


def band_points(reconstruction: pycolmap.Reconstruction, image_i: pycolmap.Image, image_j: pycolmap.Image,
                plane: Plane | None, grid: int = 15, num_depths: int = 48,
                min_points: int = 12) -> tuple[np.ndarray, np.ndarray, str]:
    """Analysis points of a pair (module docstring, 3.): pixels of image i (N x 2) and their depths in camera i
    (N), kind ``floor`` or ``depths``; empty when the images share no view."""
    camera_i, camera_j = (reconstruction.cameras[im.camera_id] for im in (image_i, image_j))
    pixels = grid_pixels(camera_i, grid)
    rays = np.column_stack([np.asarray(camera_i.cam_from_img(pixels)), np.ones(len(pixels))])
    cam_i_from_world, cam_j_from_world = image_i.cam_from_world(), image_j.cam_from_world()
    j_from_i = cam_j_from_world * cam_i_from_world.inverse()
    m = j_from_i.matrix()
    if plane is not None:
        world_from_i = cam_i_from_world.inverse()
        origin = np.asarray(world_from_i.translation)
        directions = rays @ world_from_i.rotation.matrix().T
        s = plane.intersect(np.broadcast_to(origin, directions.shape), directions)
        finite = np.isfinite(s)
        depth = s[finite]  # directions = R^T [x, y, 1]: the ray parameter is the depth in camera i
        in_i = rays[finite] * depth[:, None]
        seen = project(camera_j, in_i @ m[:, :3].T + m[:, 3])[1]
        if seen.sum() >= min_points:
            return pixels[finite][seen], depth[seen], "floor"
    distance = float(np.linalg.norm(j_from_i.translation))
    depths = 1.0 / np.linspace(1.0 / (0.1 * distance), 1.0 / (100.0 * distance), num_depths)
    in_i = (rays[:, None, :] * depths[None, :, None]).reshape(-1, 3)
    seen = project(camera_j, in_i @ m[:, :3].T + m[:, 3])[1]
    all_pixels = np.repeat(pixels, num_depths, axis=0)
    all_depths = np.tile(depths, len(pixels))
    return all_pixels[seen], all_depths[seen], "depths"


# ------------------------------------------------------------------------------------------------------------
# 3. The band


def epipolar_lines(camera_i: pycolmap.Camera, camera_j: pycolmap.Camera, j_from_i: pycolmap.Rigid3d,
                   pixels_i: np.ndarray) -> np.ndarray:
    """Lines (a, b, c) in camera j's pinhole pixels for raw pixels of image i (distortion removed)."""
    rays = np.asarray(camera_i.cam_from_img(np.asarray(pixels_i, dtype=np.float64)))
    rays = np.column_stack([rays, np.ones(len(rays))])
    essential = np.asarray(pycolmap.essential_matrix_from_pose(j_from_i))
    k_j = np.asarray(camera_j.calibration_matrix())
    return (np.linalg.inv(k_j).T @ essential @ rays.T).T


def line_distances(camera_j: pycolmap.Camera, lines: np.ndarray, points_in_j: np.ndarray) -> np.ndarray:
    """Signed distance (pinhole pixels of j) of the projection of camera-j points from pixel lines."""
    k_j = np.asarray(camera_j.calibration_matrix())
    projected = points_in_j @ k_j.T
    projected = projected / projected[..., 2:3]
    return np.sum(lines * projected, axis=-1) / np.linalg.norm(lines[..., :2], axis=-1)


def _camera_steps(camera: pycolmap.Camera, variances: np.ndarray) -> np.ndarray:
    """Finite-difference step per camera parameter: a tenth of its sigma (0 where it has none)."""
    return 0.1 * np.sqrt(np.clip(variances, 0.0, None))


def _with_params(camera: pycolmap.Camera, params: np.ndarray) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=params)


def ray_jacobian(camera: pycolmap.Camera, pixels: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 2, n_params): derivative of the normalised ray ``cam_from_img(pixel)`` with respect to each camera
    parameter (central differences through pycolmap's model; zero where ``steps`` is 0)."""
    out = np.zeros((len(pixels), 2, len(steps)))
    params = np.asarray(camera.params, dtype=np.float64)
    for k in np.flatnonzero(steps > 0):
        up, down = params.copy(), params.copy()
        up[k] += steps[k]
        down[k] -= steps[k]
        out[:, :, k] = (np.asarray(_with_params(camera, up).cam_from_img(pixels))
                        - np.asarray(_with_params(camera, down).cam_from_img(pixels))) / (2 * steps[k])
    return out


def projection_jacobian(camera: pycolmap.Camera, points: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 2, n_params): derivative of ``cam_from_img_estimated(img_from_cam_drawn(X))`` (the normalised
    coordinates an analyst recovers from the pixel a drawn camera sees) with respect to each parameter."""
    out = np.zeros((len(points), 2, len(steps)))
    params = np.asarray(camera.params, dtype=np.float64)
    for k in np.flatnonzero(steps > 0):
        values = []
        for sign in (1.0, -1.0):
            shifted = params.copy()
            shifted[k] += sign * steps[k]
            pixels = np.asarray(_with_params(camera, shifted).img_from_cam(points, check_cheirality=False))
            values.append(np.asarray(camera.cam_from_img(pixels)))
        out[:, :, k] = (values[0] - values[1]) / (2 * steps[k])
    return out


@dataclass(frozen=True)
class PairBand:
    band_px: float  # half-width holding the true correspondence with BAND_PROBABILITY, pooled
    points: str  # "floor" or "depths"
    num_points: int
    depth_range_m: tuple[float, float]  # of the analysis points, in camera i
    predicted_coverage: np.ndarray = field(repr=False)  # share of the pair's points inside the band, per draw

    @property
    def predicted_below_85(self) -> float:
        """Predicted probability that fewer than 85 % of this pair's points lie inside its band."""
        return float(np.mean(self.predicted_coverage < PAIR_COVERAGE_LEVEL))


class _PairModel:
    """The linear model ``d = J z`` of one pair's analysis points (module docstring, 3.)."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, covariance: JointCovariance,
                 image_i: pycolmap.Image, image_j: pycolmap.Image, ray_cache: dict):
        rec = reconstruction
        self.images = (image_i, image_j)
        self.cameras = tuple(rec.cameras[im.camera_id] for im in self.images)
        keys = []
        for image in self.images:
            for key in (("frame", image.frame_id), ("sensor_from_rig", image.camera_id), ("camera", image.camera_id)):
                if key in covariance.offsets and key not in keys:
                    keys.append(key)
        self.keys = keys
        self.columns = {key: slice(start, start + covariance.offsets[key][1])
                        for key, start in zip(keys, np.cumsum([0] + [covariance.offsets[k][1] for k in keys]))}
        self.size = sum(covariance.offsets[k][1] for k in keys)
        self.covariance = covariance.sub(keys)
        self.ray_cache = ray_cache
        self.reconstruction = rec

    def _narrow(self, image: pycolmap.Image):
        rec = self.reconstruction
        frame = rec.frame(image.frame_id)
        sensor = sensor_from_rig_view(rec, frame.rig_id, rec.cameras[image.camera_id].sensor_id)
        return frame, sensor

    def _pose_jacobian(self, image: pycolmap.Image, left: np.ndarray) -> np.ndarray:
        """(6, size): ``left`` (6x6, d relative pose / d narrow pose) times d narrow pose / d parameters."""
        frame, sensor = self._narrow(image)
        d_frame, d_sensor = narrow_tangent_jacobians(frame.rig_from_world, sensor)
        out = np.zeros((6, self.size))
        out[:, self.columns[("frame", image.frame_id)]] += left @ d_frame
        key = ("sensor_from_rig", image.camera_id)
        if key in self.columns:
            out[:, self.columns[key]] += left @ d_sensor
        return out

    def pose_jacobian(self) -> np.ndarray:
        """(6, size): ``[w, dt]`` of ``narrow_j_from_narrow_i`` by the parameters."""
        image_i, image_j = self.images
        pose_i, pose_j = image_i.cam_from_world(), image_j.cam_from_world()
        r_q = (pose_j * pose_i.inverse()).rotation.matrix()
        rt = r_q @ np.asarray(pose_i.translation)
        d_q_d_j = np.eye(6)
        d_q_d_j[3:, :3] = _skew(rt)
        d_q_d_i = np.zeros((6, 6))
        d_q_d_i[:3, :3] = -r_q
        d_q_d_i[3:, :3] = -_skew(rt) @ r_q
        d_q_d_i[3:, 3:] = -r_q
        return self._pose_jacobian(image_j, d_q_d_j) + self._pose_jacobian(image_i, d_q_d_i)

    def jacobian(self, pixels_i: np.ndarray, depths: np.ndarray) -> np.ndarray:
        """(P, size): derivative of each point's distance from its estimated line (pinhole px of j)."""
        image_i, image_j = self.images
        camera_i, camera_j = self.cameras
        pose_i, pose_j = image_i.cam_from_world(), image_j.cam_from_world()
        j_from_i = pose_j * pose_i.inverse()
        r_q = j_from_i.rotation.matrix()
        d_q = self.pose_jacobian()  # (6, size)

        normalised_i = np.asarray(camera_i.cam_from_img(pixels_i))
        x_i = np.column_stack([normalised_i, np.ones(len(pixels_i))]) * depths[:, None]
        x_j = x_i @ r_q.T + np.asarray(j_from_i.translation)
        z = x_j[:, 2]
        d_n_d_x = np.zeros((len(z), 2, 3))  # normalised coordinates in j by the point in j
        d_n_d_x[:, 0, 0] = d_n_d_x[:, 1, 1] = 1.0 / z
        d_n_d_x[:, :, 2] = -x_j[:, :2] / z[:, None] ** 2
        # the point in j: d x_j = -[R_q x_i]x w_q + dt_q + R_q d x_i
        rotated = x_i @ r_q.T
        d_x_d_q = np.zeros((len(z), 3, 6))
        d_x_d_q[:, :, :3] = -np.array([_skew(v) for v in rotated])
        d_x_d_q[:, :, 3:] = np.eye(3)
        jac = np.einsum("pab,pbk,kn->pan", d_n_d_x, d_x_d_q, d_q)  # (P, 2, size)
        variances = np.diag(self.covariance)
        key_i, key_j = ("camera", image_i.camera_id), ("camera", image_j.camera_id)
        if key_i in self.columns:
            cache_key = (image_i.name, pixels_i.tobytes())
            if cache_key not in self.ray_cache:
                self.ray_cache[cache_key] = ray_jacobian(camera_i, pixels_i, _camera_steps(camera_i, variances[self.columns[key_i]]))
            d_ray = self.ray_cache[cache_key]  # (P, 2, n)
            d_x_i = np.concatenate([d_ray, np.zeros((len(z), 1, d_ray.shape[2]))], axis=1) * depths[:, None, None]
            jac[:, :, self.columns[key_i]] += np.einsum("pab,bc,pcn->pan", d_n_d_x, r_q, d_x_i)
        if key_j in self.columns:
            jac[:, :, self.columns[key_j]] += projection_jacobian(camera_j, x_j,
                                                                  _camera_steps(camera_j, variances[self.columns[key_j]]))
        lines = epipolar_lines(camera_i, camera_j, j_from_i, pixels_i)
        k_j = np.asarray(camera_j.calibration_matrix())
        weights = np.column_stack([lines[:, 0] * k_j[0, 0], lines[:, 0] * k_j[0, 1] + lines[:, 1] * k_j[1, 1]])
        weights /= np.linalg.norm(lines[:, :2], axis=1)[:, None]
        return np.einsum("pa,pan->pn", weights, jac)


def _draw_parameters(covariance: JointCovariance, num_samples: int, seed: int) -> np.ndarray:
    """(S, all parameters): draws of the joint covariance (Cholesky root over the parameters that are not held;
    held ones, with zero rows, stay 0)."""
    free = np.flatnonzero(np.diag(covariance.covariance) > 0)
    sub = covariance.covariance[np.ix_(free, free)]
    scaling = np.sqrt(np.diag(sub))
    correlation = sub / np.outer(scaling, scaling)
    try:
        root = np.linalg.cholesky(correlation + 1e-12 * np.eye(len(free))) * scaling[:, None]
    except np.linalg.LinAlgError:  # numerically semi-definite: the eigen-root
        values, vectors = np.linalg.eigh(sub)
        root = vectors * np.sqrt(np.clip(values, 0.0, None))
    draws = np.zeros((num_samples, covariance.covariance.shape[0]))
    draws[:, free] = np.random.default_rng(seed).standard_normal((num_samples, len(free))) @ root.T
    return draws


def pooled_quantile(sigmas: np.ndarray, probability: float = BAND_PROBABILITY) -> float:
    """``b`` with ``mean_p P(|N(0, sigma_p^2)| <= b) = probability`` (bisection)."""
    sigmas = np.asarray(sigmas, dtype=np.float64)
    sigmas = np.where(sigmas > 0, sigmas, 1e-300)
    low, high = 0.0, float(sigmas.max()) * 4.0
    for _ in range(50):  # 2^-50 of the range
        middle = 0.5 * (low + high)
        if np.mean(2.0 * ndtr(middle / sigmas) - 1.0) < probability:
            low = middle
        else:
            high = middle
    return high


def narrow_pair_bands(reconstruction: pycolmap.Reconstruction, covariance: JointCovariance,
                      pairs: Sequence[tuple[str, str]] | None = None, plane: Plane | None = None,
                      num_samples: int = 400, seed: int = 0) -> dict[tuple[str, str], PairBand]:
    """:class:`PairBand` of every pair (default: every pair of registered narrow images) whose images share a
    view, with ``plane`` the floor (None: no floor, points at every depth)."""
    images = {im.name: im for im in _narrow_images(reconstruction)}
    if pairs is None:
        names = sorted(images)
        pairs = [(a, b) for k, a in enumerate(names) for b in names[k + 1:]]
    ray_cache: dict = {}
    bands = {}
    draws = None  # one set of draws of every parameter, shared by the pairs (drawn at the first pair)
    for name_i, name_j in pairs:
        image_i, image_j = images.get(name_i), images.get(name_j)
        if image_i is None or image_j is None:
            continue
        pixels, depths, kind = band_points(reconstruction, image_i, image_j, plane)
        if len(pixels) == 0:
            continue
        if draws is None:
            draws = _draw_parameters(covariance, num_samples, seed)
        model = _PairModel(reconstruction, covariance, image_i, image_j, ray_cache)
        jac = model.jacobian(pixels, depths)
        sigmas = np.sqrt(np.clip(np.einsum("pk,kl,pl->p", jac, model.covariance, jac), 0.0, None))
        band = pooled_quantile(sigmas)
        distances = draws[:, covariance.index(model.keys)] @ jac.T  # (S, P)
        coverage = np.mean(np.abs(distances) <= band, axis=1)
        bands[(name_i, name_j)] = PairBand(band, kind, len(pixels), (float(depths.min()), float(depths.max())),
                                           coverage)
    return bands


# ------------------------------------------------------------------------------------------------------------
# 3'. The band by re-adjusting over calibration draws (small networks)


def distances_under(estimate: pycolmap.Reconstruction, draw: pycolmap.Reconstruction, name_i: str, name_j: str,
                    pixels_i: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """The band's quantity without linearisation: distances (pinhole px of j) from the estimated epipolar lines of
    the correspondences that ``draw`` (a possible truth: its narrow cameras and relative pose) gives the analysis
    points (``pixels_i`` of image i at ``depths`` in camera i); NaN where a point falls behind camera j."""
    est_i, est_j = (estimate.find_image_with_name(n) for n in (name_i, name_j))
    drawn_i, drawn_j = (draw.find_image_with_name(n) for n in (name_i, name_j))
    camera_i, camera_j = estimate.cameras[est_i.camera_id], estimate.cameras[est_j.camera_id]
    rays = np.asarray(draw.cameras[drawn_i.camera_id].cam_from_img(pixels_i))
    x_i = np.column_stack([rays, np.ones(len(rays))]) * depths[:, None]
    x_j = np.asarray((drawn_j.cam_from_world() * drawn_i.cam_from_world().inverse()) * x_i)
    out = np.full(len(x_i), np.nan)
    front = x_j[:, 2] > 0
    seen = np.asarray(camera_j.cam_from_img(np.asarray(draw.cameras[drawn_j.camera_id].img_from_cam(x_j[front]))))
    lines = epipolar_lines(camera_i, camera_j, est_j.cam_from_world() * est_i.cam_from_world().inverse(), pixels_i)
    out[front] = line_distances(camera_j, lines[front], np.column_stack([seen, np.ones(len(seen))]))
    return out


def pooled_shifted_quantile(shifts: np.ndarray, sigmas: np.ndarray, probability: float = BAND_PROBABILITY) -> float:
    """``b`` with ``mean P(|shift + N(0, sigma^2)| <= b) = probability`` over all entries (bisection)."""
    sigmas = np.where(sigmas > 0, sigmas, 1e-12)
    low, high = 0.0, float(np.max(np.abs(shifts) + 6.0 * sigmas))
    for _ in range(50):
        middle = 0.5 * (low + high)
        inside = ndtr((middle - shifts) / sigmas) - ndtr((-middle - shifts) / sigmas)
        if np.mean(inside) < probability:
            low = middle
        else:
            high = middle
    return high


def sampled_pair_bands(result: AdjustResult, plane: Plane | None, num_draws: int = 40,
                       seed: int = 0) -> dict[tuple[str, str], PairBand]:
    """The band of a small network without linearising the calibration's effect: ``num_draws`` times, rigs.yaml
    moved by a draw of its priors and the network adjusted again (from the estimate; with priors centred on the
    draw when refining, as in "randomise then optimise", but with the images weighted as below); each draw's exact
    distances plus the image noise's own (linear, Gaussian) spread, pooled. The relative pose of two rigs can
    answer a calibration error far from linearly (a 2-rig scene here: half the error moved the baseline direction
    1.6 mrad, the whole error 11 mrad).

    Each draw weighs the images by the noise of its own starting residuals (the estimate's poses under the drawn
    calibration; 0.8-1.4 px on a rendered 3-rig run against the estimate's 0.18 px), not by the estimate's: the
    images then hold the draws back less than the estimate's posterior would. Measured on 24 rendered 3-rig
    networks: 0.953 coverage this way, 0.900 with the estimate's noise (no better than the linear band's 0.901),
    benchmarks/README "The sampled band against the linear one on rendered 3-rig networks"."""
    from dataclasses import replace

    from rigsfm.run.adjustment.adjust import adjust

    estimate = result.reconstruction
    image_covariance = joint_covariance(result, image_only=True)
    rng = np.random.default_rng(seed)
    draws = []
    options = replace(result.options, max_rounds=1)  # from the estimate, its outliers already gone: one solve
    priors = result.priors or calibration_priors(result.rigs)
    for _ in range(num_draws):
        try:
            draws.append(adjust(estimate, draw_calibration(result.rigs, priors, rng), result.scale_spec, options,
                                result.priors, with_covariance=False, held_rigs=result.held_rigs).reconstruction)
        except ReconstructionError as error:
            logger.info("A calibration draw failed to adjust: %s", error)
    images = {im.name: im for im in _narrow_images(estimate)}
    names = sorted(images)
    bands = {}
    for k, name_i in enumerate(names):
        for name_j in names[k + 1:]:
            pixels, depths, kind = band_points(estimate, images[name_i], images[name_j], plane)
            if len(pixels) == 0 or not draws:
                continue
            shifts = np.array([distances_under(estimate, draw, name_i, name_j, pixels, depths) for draw in draws])
            shifts = np.where(np.isfinite(shifts), shifts, 1e6)  # behind camera j: outside any band
            if image_covariance is not None:
                model = _PairModel(estimate, image_covariance, images[name_i], images[name_j], {})
                jac = model.jacobian(pixels, depths)
                sigmas = np.sqrt(np.clip(np.einsum("pk,kl,pl->p", jac, model.covariance, jac), 0.0, None))
            else:
                sigmas = np.zeros(len(pixels))
            sigmas = np.broadcast_to(sigmas, shifts.shape)
            band = pooled_shifted_quantile(shifts, sigmas)
            inside = ndtr((band - shifts) / np.maximum(sigmas, 1e-12)) - ndtr((-band - shifts) / np.maximum(sigmas, 1e-12))
            bands[(name_i, name_j)] = PairBand(band, kind, len(pixels), (float(depths.min()), float(depths.max())),
                                               inside.mean(axis=1))
    return bands


# ------------------------------------------------------------------------------------------------------------
# The stage


@dataclass
class Uncertainty:
    covariance: JointCovariance | None
    narrow: dict[str, NarrowUncertainty]
    bands: dict[tuple[str, str], PairBand]
    floor: str  # where the band's analysis points come from: floor_fit (the world stage), known_lengths, points, none
    seconds: dict[str, float]
    sampled: bool = False  # bands re-adjusted over calibration draws (sampled_pair_bands), not linear


# Networks this small get the sampled band (sampled_pair_bands). On 24 rendered 3-rig networks it covered 0.953 of
# the true floor correspondences, the linear band 0.901 (benchmarks/README, benchmarks/three_rig_bands.py).
SAMPLED_BAND_MAX_FRAMES = 3


def estimate_uncertainty(result: AdjustResult, num_samples: int = 400, seed: int = 0,
                         sampled: bool | None = None, floor: Plane | None = None) -> Uncertainty:
    """The joint covariance (reused from ``result`` when the adjustment computed it), every narrow camera's
    uncertainty and every overlapping pair's band: linear (``narrow_pair_bands``), or re-adjusted over
    calibration draws (``sampled_pair_bands``; default for networks of at most ``SAMPLED_BAND_MAX_FRAMES``
    registered frames). The bands' analysis points lie on ``floor`` (the world stage's floor fit, in
    ``result.reconstruction``'s frame) when given, else on :func:`find_floor`'s."""
    start = time.perf_counter()
    covariance = result.covariance
    if covariance is None:
        try:
            covariance = joint_covariance(result)
        except ReconstructionError as error:
            logger.warning("No joint covariance: %s", error)
    result.covariance = covariance
    seconds = {"covariance": covariance.seconds if covariance is not None else time.perf_counter() - start}
    if covariance is None:
        return Uncertainty(None, {}, {}, "none", seconds)
    start = time.perf_counter()
    narrow = narrow_uncertainty(result.reconstruction, covariance)
    plane: Plane | None
    if floor is not None:
        plane, floor_source = floor, "floor_fit"
    else:
        plane, floor_source = find_floor(result.reconstruction, result.scale_spec)
    if sampled is None:
        sampled = result.reconstruction.num_reg_frames() <= SAMPLED_BAND_MAX_FRAMES
    if sampled:
        bands = sampled_pair_bands(result, plane, seed=seed)
    else:
        bands = narrow_pair_bands(result.reconstruction, covariance, plane=plane, num_samples=num_samples, seed=seed)
    seconds["bands"] = time.perf_counter() - start
    logger.info("Uncertainty: covariance %.1f s, %d %s bands %.1f s", seconds["covariance"], len(bands),
                "sampled" if sampled else "linear", seconds["bands"])
    return Uncertainty(covariance, narrow, bands, floor_source, seconds, sampled)


# ------------------------------------------------------------------------------------------------------------
# Validation against ground truth (tests, benchmarks)


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


def calibration_changes(result: AdjustResult, covariance: JointCovariance | None) -> dict[str, dict]:
    """Per camera ``<rig>/<sensor>`` with refined intrinsics: focal and principal-point change from rigs.yaml and
    their posterior sigma; per narrow camera also E^sl's rotation (deg) and translation (mm) change and sigma.
    Empty for a fixed calibration."""
    if result.calibration != Calibration.REFINE:
        return {}
    rec = result.reconstruction
    by_name = {rig.name: rig for rig in result.rigs}
    out = {}
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        name = name_of(image)
        if not image.has_pose or name.camera in out or name.rig not in by_name:
            continue
        camera = rec.cameras[image.camera_id]
        before = by_name[name.rig].camera(name.sensor)
        row = {"focal_change_percent": 100.0 * (camera.mean_focal_length() / before.mean_focal_length() - 1.0),
               "principal_point_change_px": float(np.hypot(camera.principal_point_x - before.principal_point_x,
                                                           camera.principal_point_y - before.principal_point_y))}
        key = ("camera", image.camera_id)
        row["observed"] = bool(covariance is not None and key in covariance.offsets and key not in covariance.prior_only)
        if name.is_narrow:
            frame = rec.frame(image.frame_id)
            sensor = sensor_from_rig_view(rec, frame.rig_id, camera.sensor_id)
            prior = by_name[name.rig].narrow_from_wide
            delta = sensor.rotation * prior.rotation.inverse()
            row["narrow_from_wide_rotation_change_deg"] = float(np.degrees(delta.angle()))
            row["narrow_from_wide_translation_change_mm"] = 1000.0 * float(
                np.linalg.norm(np.asarray(sensor.translation) - np.asarray(prior.translation)))
            sensor_key = ("sensor_from_rig", image.camera_id)
            if covariance is not None and sensor_key in covariance.offsets:
                sigma = covariance.sigma(sensor_key)
                row["narrow_from_wide_rotation_sigma_deg"] = float(np.degrees(np.linalg.norm(sigma[:3])))
                row["narrow_from_wide_translation_sigma_mm"] = 1000.0 * float(np.linalg.norm(sigma[3:]))
        out[name.camera] = row
    return out


def uncertainty_summary(result: AdjustResult, uncertainty: Uncertainty):
    """The summary.json record of the uncertainty stage (``rigsfm.core.summary.UncertaintySummary``)."""
    from rigsfm.core.summary import NarrowUncertaintySummary, PairBandSummary, UncertaintySummary

    covariance = uncertainty.covariance
    return UncertaintySummary(
        calibration=str(result.calibration),
        covariance=None if covariance is None else covariance.kind,
        pixel_sigma_px=None if covariance is None else covariance.pixel_sigma,
        floor=uncertainty.floor,
        bands="sampled" if uncertainty.sampled else "linear",
        narrow={name: NarrowUncertaintySummary(centre_sigma_mm=u.centre_sigma_mm, rotation_sigma_deg=u.rotation_sigma_deg)
                for name, u in uncertainty.narrow.items()},
        pairs=[PairBandSummary(i=i, j=j, band_px=b.band_px, points=b.points, predicted_below_85=b.predicted_below_85)
               for (i, j), b in sorted(uncertainty.bands.items())],
        refined_calibration=calibration_changes(result, covariance),
    )
