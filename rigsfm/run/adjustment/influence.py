"""A track's influence on the refined calibration: how far deleting it would move the intrinsics and E^sl.

:func:`track_influence` scores every 3D point of a refined adjustment from the adjustment's own linearisation, no
truth: Ceres' Jacobian of the joint problem at the solution (``JointProblem``, the priors in), each observation's
two rows weighted by the robust loss's ``sqrt(rho')`` there (IRLS: the adjustment is an M-estimator, and an
observation the loss already gives up on does not pull). With a track's point eliminated, its reduced Jacobian
``A = P J_a`` and residual ``e = P r`` (``P`` the projector off the point's 3 columns), deleting the track moves the
other parameters by ``d = H^-1 A^T (I - L)^-1 e`` (Woodbury downdate of the reduced normal matrix ``H``; ``L = A H^-1
A^T`` the track's leverage). The score is Cook's distance on the calibration, ``D = d_c^T Sigma_c^-1 d_c`` with
``Sigma_c = sigma^2 (H^-1)_cc`` the posterior's calibration block: ``D = 1`` is a track that alone moves the refined
calibration by one posterior sigma.

Why: on a crowd a few matches across walking bodies survive as two-view tracks that the epipolar geometry happens to
allow; after adjustment they fit (one degree of freedom), so no residual test sees them, but they pull the refined
calibration by several sigma (benchmarks/README.md, "A track's influence on the refined calibration"). The repeated
views' and narrow pairs' correlation weights of the covariance (module covariance) are left out: the score ranks
tracks, and those weights change the posterior's size, not which tracks pull.
"""

from __future__ import annotations

import logging

import numpy as np
import pyceres
import pycolmap
import scipy.sparse as sp

from rigsfm.run.adjustment.covariance import DAMPING, _inverse, _row_points, parameter_entries
from rigsfm.run.adjustment.model import estimate_pixel_sigma
from rigsfm.run.adjustment.priors import calibration_priors
from rigsfm.run.adjustment.problem import JointProblem, jacobian_csr
from rigsfm.run.adjustment.result import AdjustResult
from rigsfm.run.options import Loss

logger = logging.getLogger(__name__)


def loss_weights(squared: np.ndarray, loss: Loss, scale: float) -> np.ndarray:
    """``rho'(s)`` of COLMAP's robust losses at the squared residual norms ``s`` (px^2), scale ``scale`` (px)."""
    ratio = squared / scale**2
    if loss == Loss.CAUCHY:
        return 1.0 / (1.0 + ratio)
    if loss == Loss.SOFT_L1:
        return 1.0 / np.sqrt(1.0 + ratio)
    if loss == Loss.HUBER:
        return np.where(ratio <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(ratio, 1.0)))
    return np.ones_like(squared)


def track_influence(result: AdjustResult) -> dict[int, float]:
    """Per 3D point id of ``result`` (a refined adjustment; not modified): the track's Cook's distance on the
    refined calibration (module docstring). Empty when nothing is refined or the problem is rank deficient."""
    rec = pycolmap.Reconstruction(result.reconstruction)
    options = result.options
    pixel_sigma = result.pixel_sigma or estimate_pixel_sigma(rec, options.max_reprojection_error_px)
    jp = JointProblem(rec, result.rigs, result.priors or calibration_priors(result.rigs), result.scale_spec, options,
                      pixel_sigma, gauge=result.gauge, robust=False, with_priors=True, held_rigs=result.held_rigs)
    # (calibration?, block, tangent dims) of the variable blocks, in the covariance's order
    variable = [(key[0] != "frame", block, dims) for key, block, _, dims in parameter_entries(jp)[0]
                if block is not None]
    calibration = np.concatenate([np.full(len(dims), is_calibration) for is_calibration, _, dims in variable]
                                 + [np.zeros(0, dtype=bool)])
    if not calibration.any():
        return {}
    end_points = [p for p in jp.end_points if jp.has_variable(p)]
    point_ids = [pid for pid, p in rec.points3D.items() if jp.has_variable(p.xyz)]
    evaluate = pyceres.EvaluateOptions()
    evaluate.set_parameter_blocks([b for _, b, _ in variable] + end_points + [rec.points3D[p].xyz for p in point_ids])
    num_a = len(calibration) + 3 * len(end_points)
    calibration = np.r_[calibration, np.zeros(3 * len(end_points), dtype=bool)]
    jac = jacobian_csr(jp.problem.evaluate_jacobian(evaluate)).tocsr()
    residuals = np.asarray(jp.problem.evaluate_residuals(evaluate), dtype=np.float64)
    row_point = _row_points(jac, num_a, len(point_ids))

    # The loss's weights at the solution: an observation is a pair of rows of one point.
    on_point = np.flatnonzero(row_point < len(point_ids))
    if len(on_point) % 2 or np.any(row_point[on_point[0::2]] != row_point[on_point[1::2]]):
        raise RuntimeError("track influence: the observations' residuals are not in pairs of rows")
    squared = residuals[on_point[0::2]] ** 2 + residuals[on_point[1::2]] ** 2
    weights = np.ones(len(residuals))
    weights[on_point] = np.repeat(np.sqrt(loss_weights(squared, options.loss, options.loss_scale_px)), 2)
    jac = (sp.diags(weights) @ jac).tocsr()
    residuals = residuals * weights

    # Each point eliminated: its rows projected off the point, and its Schur complement's share of H. The points go
    # in batches of one shape (rows x the pose and calibration columns they touch): numpy per batch, not per point.
    batches, schur_at, schur = [], [], []
    for index, cols, j_a, j_p, e in _point_blocks(jac, residuals, row_point, num_a, len(point_ids)):
        on_point = j_p @ np.linalg.inv(_t(j_p) @ j_p + DAMPING * np.eye(3)) @ _t(j_p)  # I - P
        schur_at.append((cols[:, :, None] * num_a + cols[:, None, :]).ravel())
        schur.append((_t(j_a) @ on_point @ j_a).ravel())
        batches.append((index, cols, j_a - on_point @ j_a, e - (on_point @ e[..., None])[..., 0]))
    h = (jac[:, :num_a].T @ jac[:, :num_a]).toarray()
    if schur:
        h -= np.bincount(np.concatenate(schur_at), np.concatenate(schur), minlength=num_a**2).reshape(num_a, num_a)
    h_inv = _inverse(0.5 * (h + h.T))
    if h_inv is None:
        logger.warning("Track influence not computed: the adjustment's normal matrix is rank deficient")
        return {}
    cal = np.flatnonzero(calibration)
    information = np.linalg.inv(h_inv[np.ix_(cal, cal)]) / jp.weight_sigma**2  # Sigma_c^-1
    h_cal = h_inv[cal]
    scores: dict[int, float] = {}
    for index, cols, a, e in batches:
        system = np.eye(a.shape[1]) - a @ h_inv[cols[:, :, None], cols[:, None, :]] @ _t(a)  # I - L
        # I - L has eigenvalues in [0, 1]: near 0, the track alone fixes some direction, and deleting it is no downdate
        solvable = np.linalg.eigvalsh(system)[:, 0] > MIN_EIGENVALUE
        x = np.linalg.solve(system[solvable], e[solvable][..., None])
        y = (_t(a[solvable]) @ x)[..., 0]  # A^T (I - L)^-1 e on the track's columns; d = H^-1 of it
        g, c = y.shape
        on_columns = sp.csr_matrix((y.ravel(), cols[solvable].ravel(), np.arange(0, g * c + 1, c)), shape=(g, num_a))
        change = np.asarray(on_columns @ h_cal.T)
        distance = np.einsum("gi,ij,gj->g", change, information, change)
        scores.update(zip((point_ids[i] for i in index[solvable]), distance.tolist()))
    return scores


MIN_EIGENVALUE = 1e-9  # of a track's I - L: below it the track is all that fixes some direction (not scored)


def _t(batch: np.ndarray) -> np.ndarray:
    return np.swapaxes(batch, -1, -2)


def _point_blocks(jac: sp.csr_matrix, residuals: np.ndarray, row_point: np.ndarray, num_a: int, num_points: int):
    """The observations of each point as dense blocks, in batches of points of one shape: ``(index, cols, j_a, j_p,
    e)`` with ``index`` [G] the points' positions, ``cols`` [G, c] the columns of the first ``num_a`` they touch,
    ``j_a`` [G, r, c] and ``j_p`` [G, r, 3] their Jacobian's rows, ``e`` [G, r] their residuals."""
    rows = np.flatnonzero(row_point < num_points)
    rows = rows[np.argsort(row_point[rows], kind="stable")]  # grouped by point
    point_of_row = row_point[rows]
    first_row = np.searchsorted(point_of_row, np.arange(num_points + 1))
    num_rows = np.diff(first_row)
    coo = jac[rows].tocoo()
    point = point_of_row[coo.row]
    local_row = coo.row - first_row[point]
    is_a = coo.col < num_a
    # the point's own columns: 3 per point, in order
    j_p_all = np.zeros((len(rows), 3))
    j_p_all[coo.row[~is_a], coo.col[~is_a] - num_a - 3 * point[~is_a]] = coo.data[~is_a]
    keys, inverse = np.unique(point[is_a].astype(np.int64) * num_a + coo.col[is_a], return_inverse=True)
    first_key = np.searchsorted(keys // num_a, np.arange(num_points + 1))
    num_cols = np.diff(first_key)
    local_col = inverse - first_key[point[is_a]]
    shapes, shape_of = np.unique(np.column_stack([num_rows, num_cols]), axis=0, return_inverse=True)
    shape_of = shape_of.ravel()
    points_by_shape = np.argsort(shape_of, kind="stable")
    first_point = np.searchsorted(shape_of[points_by_shape], np.arange(len(shapes) + 1))
    position = np.empty(num_points, dtype=np.int64)  # of a point in its batch
    position[points_by_shape] = np.arange(num_points) - first_point[shape_of[points_by_shape]]
    a_point, a_row, a_value = point[is_a], local_row[is_a], coo.data[is_a]
    entries_by_shape = np.argsort(shape_of[a_point], kind="stable")
    first_entry = np.searchsorted(shape_of[a_point][entries_by_shape], np.arange(len(shapes) + 1))
    residuals = residuals[rows]
    for s, (r, c) in enumerate(shapes):
        index = points_by_shape[first_point[s]:first_point[s + 1]]
        mine = entries_by_shape[first_entry[s]:first_entry[s + 1]]
        j_a = np.zeros((len(index), r, c))
        j_a[position[a_point[mine]], a_row[mine], local_col[mine]] = a_value[mine]
        cols = (keys[first_key[index][:, None] + np.arange(c)] % num_a).astype(np.int64)
        row_index = first_row[index][:, None] + np.arange(r)
        yield index, cols, j_a, j_p_all[row_index], residuals[row_index]
