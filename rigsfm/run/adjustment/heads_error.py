"""An error shared by one view's heads, in the covariance of the adjustment with them.

A head centre (``rigsfm.run.narrow.heads``: a Hough circle refined to a silhouette's edge) errs by its own noise
(``point_sigmas``, per head) and possibly by a part every head of the view shares: an offset, and a tilt across the
view (lighting, occlusion and perspective alike in one image). One narrow camera per frame sees its heads once, so an
offset is a rotation of the camera to first order and a tilt mostly its focal lengths and roll: the adjustment takes
them into the narrow camera, and the heads' residuals cannot show them (no estimate of their size from a run's own
residuals: ``AdjustResult.point_shared_sigma`` is given, zero in a run; benchmarks/README.md has what the rendered
crowds' truth says of them).

The estimate stays the adjustment's (the heads weighed as independent); its covariance becomes that estimator's
under ``e = b_v + s_v . (p - c_v) / h_v + w``: per view ``v`` and image coordinate, an offset ``b_v`` of standard
deviation ``shared_sigma`` and a tilt ``s_v`` (one per image axis) of ``shared_slope_sigma`` at the edge of the view's
heads (``c_v`` their centre, ``h_v`` half their extent), ``w`` the head's own noise. With the points eliminated
(``J~`` the reduced rows, ``S`` the Schur complement the covariance inverts), the sandwich
``Cov = sigma^2 S^-1 (S + sum u u^T) S^-1``, one ``u`` per view, coordinate and term: the view's reduced head rows of
that coordinate summed, each times the term's value at its head over the head's sigma. ``S^-1 u`` is the estimate's
response to that term, so the added covariance is the spread of the estimate over the shared errors' draws."""

from __future__ import annotations

import numpy as np
import pyceres
import scipy.sparse as sp

from rigsfm.run.adjustment.problem import jacobian_csr


def shared_view_information(problem: pyceres.Problem, view_blocks: dict[int, list[tuple[object, float, np.ndarray]]],
                            parameter_blocks: list, num_a: int, h_pp_inv: sp.spmatrix | None,
                            h_ap: sp.spmatrix | None, shared_sigma: float,
                            slope_sigma: float = 0.0) -> np.ndarray | None:
    """``sum u u^T`` (module docstring) over the first ``num_a`` columns of the reduced system of ``problem`` whose
    columns are ``parameter_blocks`` (points last, eliminated by ``h_pp_inv`` and ``h_ap``), in its units (residuals
    at the images' weighting noise); ``view_blocks``: image_id -> (residual block, its point's sigma px, keypoint)
    per head observation (``JointProblem.point_sigma_blocks``). None when nothing is shared."""
    blocks = [(block, sigma) for image_id in sorted(view_blocks) for block, sigma, _ in view_blocks[image_id]]
    if (shared_sigma <= 0 and slope_sigma <= 0) or not blocks:
        return None
    evaluate = pyceres.EvaluateOptions()
    evaluate.set_parameter_blocks(parameter_blocks)
    evaluate.set_residual_blocks([block for block, _ in blocks])
    jac = jacobian_csr(problem.evaluate_jacobian(evaluate))
    if jac.shape[0] != 2 * len(blocks):
        raise RuntimeError("a head's residual block without two residuals")
    rows, groups, weights = [], [], []
    k = 0
    for g, image_id in enumerate(sorted(view_blocks)):
        xy = np.array([p for _, _, p in view_blocks[image_id]])
        centre, half = xy.mean(0), np.maximum(0.5 * np.ptp(xy, axis=0), 1.0)
        for (_, sigma, p) in view_blocks[image_id]:
            basis = [shared_sigma, *(slope_sigma * (p - centre) / half)]
            for b, value in enumerate(basis):
                rows += [2 * k, 2 * k + 1]
                groups += [6 * g + 2 * b, 6 * g + 2 * b + 1]
                weights += [value / sigma] * 2
            k += 1
    summing = sp.csr_matrix((weights, (groups, rows)), shape=(6 * len(view_blocks), jac.shape[0]))
    summed = summing @ jac
    u = summed[:, :num_a].toarray()
    if h_pp_inv is not None and h_ap is not None and summed.shape[1] > num_a:
        u -= (summed[:, num_a:] @ h_pp_inv @ h_ap.T).toarray()
    return u.T @ u
