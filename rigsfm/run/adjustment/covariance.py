"""The joint covariance of rig poses and calibration, 3D points marginalised out.

:func:`joint_covariance`: the covariance of every rig pose, E^sl and camera (3D points marginalised out). Ceres'
Jacobian of the adjustment's own problem (``rigsfm.run.adjustment.problem.JointProblem``, squared loss: the inliers'
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
A parameter no image observes keeps its prior, independent of the rest (``prior_only``). A camera's repeated views of
a point (a static rig's frames) are weighed as correlated observations (``rigsfm.run.adjustment.repeated``), and so are
a narrow pair's matches (``rigsfm.run.adjustment.correlated``); an error shared by one view's heads, where given,
widens it as the estimator's own covariance (``rigsfm.run.adjustment.heads_error``)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyceres
import pycolmap
import scipy.linalg
import scipy.sparse as sp

from rigsfm.core.geometry import skew
from rigsfm.run.adjustment.correlated import correlated_point_weights
from rigsfm.run.adjustment.heads_error import shared_view_information
from rigsfm.run.adjustment.model import estimate_pixel_sigma, sensor_from_rig_view
from rigsfm.run.adjustment.priors import calibration_priors
from rigsfm.run.adjustment.problem import JointProblem, jacobian_csr
from rigsfm.run.adjustment.repeated import repeated_view_correlation, repeated_view_weights
from rigsfm.run.adjustment.result import AdjustResult, Gauge, JointCovariance, ScaleSource
from rigsfm.run.options import Calibration

logger = logging.getLogger(__name__)


DAMPING = 1e-8  # added to each point's 3x3 block in the Schur complement
EXCESS_ROWS_PER_CHUNK = 5000  # residual rows per dense block in _change_excess (x the calibration's columns)
RANK_TOLERANCE = 1e-10  # smallest / largest eigenvalue of the Jacobi-scaled reduced normal matrix


def parameter_entries(jp: JointProblem) -> tuple[list[tuple[tuple, Any, int, Any]], dict[tuple, np.ndarray]]:
    """The parameters of ``jp`` other than the points, in the reduced system's order (frames, narrow
    ``sensor_from_rig``, cameras): every entry ``(key, block or None, size, tangent dims or None)``, ``key`` one of
    ``("frame", frame_id)``, ``("sensor_from_rig", camera_id)``, ``("camera", camera_id)``, the block None where it is
    constant; and the prior covariance of each constant calibration block, by key."""
    rec = jp.reconstruction
    entries: list[tuple[tuple, Any, int, Any]] = []
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
    return entries, prior_only


def _reduced_system(jp: JointProblem, max_error_px: float | None = None, inflation: float = 1.0,
                    calibration_held: frozenset[str] | None = None, shared_sigma: float = 0.0,
                    shared_slope_sigma: float = 0.0):
    """Ceres' Jacobian of ``jp`` (tangent space) with the points eliminated (Schur complement, 3x3 blocks): the
    reduced normal matrix over the other blocks, every entry ``(key, block or None, size, tangent dims)``, the
    variable ones, the prior-only covariances, and the heads' shared error's term beside the matrix (module
    heads_error; None without one); None (with a warning) when a point carries no information.
    ``calibration_held``: the rigs whose calibration the estimate held (None: every rig's, ``FIXED``), for the
    narrow pairs' weights (module correlated); ``shared_sigma``, ``shared_slope_sigma``: the heads' shared error
    per view (``AdjustResult.point_shared_sigma``)."""
    rec, problem = jp.reconstruction, jp.problem
    entries, prior_only = parameter_entries(jp)
    variable = [entry for entry in entries if entry[1] is not None]
    end_points = [p for p in jp.end_points if jp.has_variable(p)]
    point_ids = [point_id for point_id, p in rec.points3D.items() if jp.has_variable(p.xyz)]
    points = [rec.points3D[point_id].xyz for point_id in point_ids]
    blocks = [block for _, block, _, _ in variable] + end_points + points
    for key, block, _, dims in variable:
        if problem.parameter_block_tangent_size(block) != len(dims):
            raise RuntimeError(f"unexpected tangent size of {key}")
    evaluate = pyceres.EvaluateOptions()
    evaluate.set_parameter_blocks(blocks)
    num_a = sum(len(dims) for _, _, _, dims in variable) + 3 * len(end_points)
    jac = jacobian_csr(problem.evaluate_jacobian(evaluate))
    repeated = np.ones(jac.shape[0])
    rho = repeated_view_correlation(rec, inflation, max_error_px)
    if rho:  # a static rig's repeated views are not independent observations (module repeated)
        camera_of_column = np.concatenate([np.full(len(dims), key[1] if key[0] == "camera" else -1)
                                           for key, _, _, dims in variable] + [np.full(3 * len(end_points), -1)])
        repeated = repeated_view_weights(jac, num_a, camera_of_column.astype(np.int64), rho)
        logger.info("Covariance: repeated views of a point by one camera weighed as correlated (%d cameras, "
                    "correlation %.2f-%.2f)", len(rho), min(rho.values()), max(rho.values()))
    narrow_cameras = {camera_id for _, _, camera_id, _ in jp.narrow_sensors()}
    held_cameras = {c for c in narrow_cameras if calibration_held is None or jp.camera_names[c].rig in calibration_held}
    point_weights = correlated_point_weights(rec, narrow_cameras, point_ids, jp.weight_sigma, inflation, held_cameras)
    if point_weights is not None:  # a narrow pair's matches share a smooth error (module correlated)
        # ... not the points weighed at their own noise already (heads: JointProblem.point_sigmas)
        point_weights[[k for k, point_id in enumerate(point_ids) if point_id in jp.point_sigmas]] = 1.0
        jac = sp.diags(np.r_[point_weights, 1.0][_row_points(jac.tocsr(), num_a, len(point_ids))]) @ jac
    # Only the repeated views' weights enter the test's excess (_change_excess), not the narrow pairs': without them
    # the benign networks with narrow observations already sat at their chi-square's dof, and with them a 1 % wide
    # focal error in rigs.yaml passed the test (benchmarks/README.md, "the solve counts repeated views in full").
    estimator = _EstimatorRows(jac.tocsc(), repeated, num_a) if np.any(repeated != 1.0) else None
    if estimator is not None:
        jac = sp.diags(repeated) @ jac
    schur = _schur(jac.tocsc(), num_a)
    if schur is None:
        logger.warning("No joint covariance: some 3D points carry no information (every observation of them is "
                       "degenerate or cannot be projected)")
        return None
    shared = shared_view_information(jp.problem, jp.point_sigma_blocks, blocks, num_a, schur.h_pp_inv, schur.h_ap,
                                     shared_sigma, shared_slope_sigma)
    return schur.matrix, entries, variable, prior_only, shared, estimator


@dataclass(frozen=True)
class _Schur:
    """The reduced normal matrix over the non-point columns (points eliminated), and the pieces of the elimination."""

    matrix: np.ndarray
    h_pp_inv: Any
    h_ap: Any


def _schur(jac: sp.csc_matrix, num_a: int) -> _Schur | None:
    """The points (columns after ``num_a``, 3 each) eliminated from ``jac``'s normal matrix; None when a point's
    3x3 block is missing (it carries no information)."""
    j_a, j_p = jac[:, :num_a], jac[:, num_a:]
    h_aa = (j_a.T @ j_a).toarray()
    if not j_p.shape[1]:
        return _Schur(0.5 * (h_aa + h_aa.T), None, None)
    h_pp = (j_p.T @ j_p).tobsr(blocksize=(3, 3))
    num_points = j_p.shape[1] // 3
    if not (np.array_equal(h_pp.indices, np.arange(num_points))
            and np.array_equal(h_pp.indptr, np.arange(num_points + 1))):
        return None
    inverse = np.linalg.inv(h_pp.data + DAMPING * np.eye(3))
    h_pp_inv = sp.bsr_matrix((inverse, np.arange(num_points), np.arange(num_points + 1)), shape=h_pp.shape)
    h_ap = (j_a.T @ j_p).tocsr()
    schur = h_aa - (h_ap @ h_pp_inv @ h_ap.T).toarray()
    return _Schur(0.5 * (schur + schur.T), h_pp_inv, h_ap)


@dataclass(frozen=True)
class _EstimatorRows:
    """The Jacobian the consistency test takes for the solve's (every repeated view at full weight, as the solve
    counts it) and the covariance's weights of its rows (``w < 1``: a repeated view the noise model counts as worth
    ``w^2`` of an independent one)."""

    jacobian: sp.csc_matrix
    weights: np.ndarray
    num_a: int


def _change_excess(estimator: _EstimatorRows, columns: np.ndarray, posterior: np.ndarray, factors: np.ndarray,
                   weight_sigma: float) -> np.ndarray | None:
    """How much wider the spread of the adjustment's calibration change is than ``prior - posterior`` (its spread
    were the solve weighted as the covariance's noise model), over ``columns`` (our tangents; ``posterior`` their
    block of the covariance's posterior, ``factors`` their tangent factors); None when rank deficient.

    The solve weighs every residual alike (``M = J^T J`` with the priors' rows), the noise model counts row ``i`` as
    ``w_i^2`` of an independent residual (variance ``s^2 / w_i^2``). With ``Y = M^-1 E`` (``E`` the calibration's
    columns) and ``P_e = s^2 E^T M^-1 E`` the solve's own posterior, the change ``c - c_yaml`` has the spread
    ``P0 - P_e + s^2 (J Y)^T diag(1 / w^2 - 1) (J Y)`` (``P0`` the prior; the prior's and every unit-weight row's
    share cancels), against ``P0 - P`` with the noise model's posterior ``P``: the excess is
    ``P - P_e + s^2 (J Y)^T diag(1 / w^2 - 1) (J Y)``. The solve trusts the down-weighted residuals (a static rig's
    repeated views of one point) as independent, so it moves the calibration further than ``P`` explains."""
    jac, num_a = estimator.jacobian, estimator.num_a
    schur = _schur(jac, num_a)
    if schur is None:
        return None
    inverse = _inverse(schur.matrix)
    if inverse is None:
        return None
    y_a = inverse[:, columns]
    extra = 1.0 / estimator.weights**2 - 1.0
    rows = np.flatnonzero(extra > 0)  # a unit-weight row adds nothing
    csr = jac.tocsr()
    if schur.h_ap is not None:
        h_pa, h_pp_inv = schur.h_ap.T.tocsr(), schur.h_pp_inv.tocsr()
    meat = np.zeros((len(columns), len(columns)))
    for start in range(0, len(rows), EXCESS_ROWS_PER_CHUNK):  # dense blocks of (rows or points) x calibration
        chunk = csr[rows[start:start + EXCESS_ROWS_PER_CHUNK]]
        spread = chunk[:, :num_a] @ y_a
        if schur.h_ap is not None:  # the points' rows of Y = M^-1 E, only those this chunk observes
            points = np.unique((chunk.indices[chunk.indices >= num_a] - num_a) // 3)
            touched = (3 * points[:, None] + np.arange(3)).ravel()  # whole 3x3 blocks of the block-diagonal inverse
            y_p = h_pp_inv[touched][:, touched] @ (h_pa[touched] @ y_a)
            spread = spread - chunk[:, num_a:][:, touched] @ y_p
        meat += spread.T @ (spread * extra[rows[start:start + EXCESS_ROWS_PER_CHUNK], None])
    scale = weight_sigma**2 * np.outer(factors, factors)
    own = inverse[np.ix_(columns, columns)] * scale
    excess = posterior - own + 0.5 * (meat + meat.T) * scale
    return 0.5 * (excess + excess.T)


def _row_points(jacobian: sp.csr_matrix, num_a: int, num_points: int) -> np.ndarray:
    """Per row: the index of the point whose columns it touches (``num_points``, one past the last, for rows
    of no point: index a weight array padded with 1)."""
    rows = np.repeat(np.arange(jacobian.shape[0]), np.diff(jacobian.indptr))
    point_of = np.where(jacobian.indices >= num_a, (jacobian.indices - num_a) // 3, -1)
    out = np.full(jacobian.shape[0], -1)
    np.maximum.at(out, rows, point_of)
    return np.where(out >= 0, out, num_points)


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
        logger.warning("No joint covariance: the problem is rank deficient (%s)",
                       "its Cholesky factorisation failed: not positive definite" if factor is None
                       else f"smallest Cholesky pivot {pivots.min():.3g} of {pivots.max():.3g}")
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
    pixel_sigma = result.pixel_sigma or estimate_pixel_sigma(rec, options.max_reprojection_error_px,
                                                             result.point_sigmas)
    gauge = Gauge.TWO_CAMS_FROM_WORLD if result.scale_source == ScaleSource.NONE else Gauge.RIGID
    refined = result.calibration == Calibration.REFINE and not image_only
    held = result.held_rigs if refined else frozenset()
    jp = JointProblem(rec, rigs, priors, result.scale_spec, options, pixel_sigma, gauge=gauge, robust=False,
                      with_priors=refined, held_rigs=held, consider_held=True, point_sigmas=result.point_sigmas)
    reduced = _reduced_system(jp, options.max_reprojection_error_px, options.pixel_sigma_inflation,
                              held if refined else None, result.point_shared_sigma, result.point_shared_slope_sigma)
    if reduced is None:
        return None
    schur, entries, variable, prior_only, shared, estimator = reduced
    factors = _tangent_factors(variable)
    num_end = schur.shape[0] - len(factors)
    factors = np.r_[factors, np.ones(num_end)]
    excess = None
    if refined and held:  # the refined rigs' posterior, the held rigs' calibration considered
        cov = _consider(jp, schur, variable, factors, consider_rigs=held, shared=shared)
        if cov is None:
            return None
        kind = "posterior"
    elif refined:
        inverse = _inverse(schur)
        if inverse is None:
            return None
        if shared is not None:  # the estimator's covariance under the heads' shared error (module heads_error)
            inverse = inverse + inverse @ shared @ inverse
        cov = inverse * jp.weight_sigma**2 * np.outer(factors, factors)
        kind = "posterior"
        if estimator is not None:  # the solve weighed some residuals otherwise than the noise model: its change
            excess = _calibration_excess(estimator, variable, cov, factors, jp.weight_sigma)  # spreads wider
    else:
        cov = _consider(jp, schur, variable, factors, 0.0 if image_only else 1.0, shared=shared)
        if cov is None:
            return None
        kind = "image" if image_only else "consider"
    if image_only:
        prior_only = {key: np.zeros_like(value) for key, value in prior_only.items()}
    keys, offsets, full = _assemble(entries, variable, cov, prior_only)
    change_excess = None if excess is None else _assemble(entries, variable, excess, {})[2]
    return JointCovariance(keys, offsets, full, jp.weight_sigma, kind, frozenset(prior_only),
                           time.perf_counter() - start, change_excess)


def _calibration_excess(estimator: _EstimatorRows, variable, cov: np.ndarray, factors: np.ndarray,
                        weight_sigma: float) -> np.ndarray | None:
    """:func:`_change_excess` over the calibration's variable dimensions (cameras, E^sl), zero elsewhere, in the
    layout of ``cov`` (the variable dimensions, end points last)."""
    columns: list[int] = []
    at = 0
    for key, _, _, dims in variable:
        if key[0] in ("camera", "sensor_from_rig"):
            columns.extend(range(at, at + len(dims)))
        at += len(dims)
    columns_array = np.array(columns, dtype=np.int64)
    out = np.zeros_like(cov)
    if not len(columns_array):
        return out
    block = _change_excess(estimator, columns_array, cov[np.ix_(columns_array, columns_array)],
                           factors[columns_array], weight_sigma)
    if block is None:
        return None
    out[np.ix_(columns_array, columns_array)] = block
    return out


def _consider(jp: JointProblem, schur: np.ndarray, variable, factors: np.ndarray,
              prior_weight: float = 1.0, consider_rigs: frozenset[str] | None = None,
              shared: np.ndarray | None = None) -> np.ndarray | None:
    """The consider covariance (our tangents) over the variable dimensions, end points last. ``consider_rigs``:
    only these rigs' calibration is considered, the others' is estimated with the poses (their priors in
    ``schur``); None: every rig's is considered. ``shared``: the heads' shared error's term beside ``schur``
    (module heads_error), or None."""
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
    if shared is not None:  # the estimator's covariance under the heads' shared error (module heads_error)
        a_inv = a_inv + a_inv @ (shared / np.outer(factors, factors))[np.ix_(pose_index, pose_index)] @ a_inv
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


def frame_centre_jacobian(rigid: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``-R^T t`` of a pose and its Jacobian (3x6) with respect to ``[w, dt]``."""
    r, t = rigid.rotation.matrix(), np.asarray(rigid.translation)
    return -r.T @ t, np.hstack([-r.T @ skew(t), -r.T])


def network_size_sigma(covariance: JointCovariance | None, reconstruction: pycolmap.Reconstruction) -> float | None:
    """Relative 1-sigma uncertainty of the distance between the two registered frames farthest apart: how well
    the network's size (its metric scale) is known."""
    if covariance is None:
        return None
    frames = sorted(reconstruction.reg_frame_ids())
    # registered frames have their poses
    centres = {f: frame_centre_jacobian(reconstruction.frame(f).rig_from_world) for f in frames}  # type: ignore[arg-type]
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
