"""Joint refinement: both cameras' intrinsics, E^sl and every board pose, over *all* views.

``stereoCalibrate`` with free intrinsics only sees the views both cameras share, where the wide camera
sees the board small and central, so it tends to spoil the wide distortion. Here every view of either
camera contributes (board pose in the wide frame; the narrow camera sees it through E^sl), so the wide
periphery stays constrained. Levenberg-Marquardt (Ceres, through pyceres, with a dense Schur complement that
eliminates the board poses: the minimum of scipy's MINPACK LM to 1e-8, 2.5-5x sooner) on the pixel
reprojection errors with the analytic Jacobian from ``cv2.projectPoints`` and ``cv2.composeRT``, in float64
(detected corners are float32: left so, the residuals and the Jacobian are float32 too and the fit stalls
short of the minimum), each view's errors weighted by 1 / its corner noise (estimated from the fit: it
varies 10x between frontal and tilted views; weighting halves the errors of the estimate on rendered boards).

Covariance of the intrinsics and E^sl (board poses marginalised out): (J^T W J)^-1 scaled by the weighted
residual variance RSS_w / (2N - p), which assumes independent corner errors, then inflated per block (wide
intrinsics, narrow intrinsics, E^sl) by sqrt(median over the block of jackknife variance / that variance),
at least 1, the jackknife being the linearised delete-one-frame one. On rendered boards corner errors are
independent, the factor is ~1 and the actual errors / sigmas have an RMS of 0.90-1.08 per parameter group
over 24 calibrations (benchmarks/calibration_sigmas.py). On OpenCV's real chessboard pairs the residuals of
neighbouring corners are correlated (0.3-0.5: lens-model misfit, a corner bias that repeats along the board),
the independent-error sigmas are 2.2x (intrinsics) and 1.7x (E^sl) smaller than the leave-one-frame-out
spread of the calibration, and the inflation restores them (tests/test_calibrate_real.py).

Note: a narrow principal-point shift dp is almost indistinguishable from an E^sl rotation of dp / f_narrow
rad (the narrow field of view is small), so the E^sl rotation is only as good as the narrow principal
point: it needs narrow views of a strongly tilted board. The reported std devs show this coupling.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import pyceres

from rigsfm.calibrate.intrinsics import CameraCalibration

logger = logging.getLogger(__name__)

NOISE_ITERATIONS = 8  # refits with re-estimated per-view noise levels
PRIOR_DOF = 4.0  # a view's noise estimate is shrunk towards its camera's with this many pseudo-residuals


@dataclass
class JointFit:
    K_wide: np.ndarray
    dist_wide: np.ndarray
    K_narrow: np.ndarray
    dist_narrow: np.ndarray
    R: np.ndarray
    T: np.ndarray
    rms_wide: float  # over all wide views
    rms_narrow: float  # over all narrow views
    rms_common: float  # over the views both cameras saw
    per_view: dict[str, tuple[float, float]]  # common view -> (wide RMS, narrow RMS)
    std: np.ndarray  # std dev of fx, fy, cx, cy (wide) then (narrow), px
    condition: float  # of the column-scaled normal matrix
    noise: tuple[float, float] = (float("nan"), float("nan"))  # pooled corner noise (px per coordinate): wide, narrow
    # Covariance of [wide intrinsics, narrow intrinsics, w (rad), t (m)] (see ``block``), where each camera's
    # intrinsics are fx, fy, cx, cy, k1, k2, p1, p2[, k3] (OpenCV) and w is a small rotation applied on the
    # left of E^sl's rotation (R_true = Exp(w) R); board poses marginalised out. None if singular.
    covariance: np.ndarray | None = None
    n_wide: int = 8  # number of wide intrinsics in ``covariance``
    n_narrow: int = 8
    covariance_iid: np.ndarray | None = None  # the same for independent corner noise, before the inflation
    inflation: tuple[float, float, float] = (1.0, 1.0, 1.0)  # sigma factor: wide, narrow, E^sl (see joint_refine)

    def block(self, part: str) -> np.ndarray | None:
        """Covariance block of ``part``: 'wide', 'narrow' (intrinsics) or 'rig' (6x6 [w, t])."""
        if self.covariance is None:
            return None
        a, b = self.n_wide, self.n_wide + self.n_narrow
        cut = {"wide": slice(0, a), "narrow": slice(a, b), "rig": slice(b, b + 6)}[part]
        return self.covariance[cut, cut]


def left_jacobian(r: np.ndarray) -> np.ndarray:
    """d w / d r where Exp(w) R(r) = R(r + dr), w = J_l(r) dr: the left Jacobian of SO(3) at the rotation
    vector ``r`` (OpenCV Rodrigues)."""
    theta = float(np.linalg.norm(r))
    K = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - np.cos(theta)) / theta ** 2 * K + (theta - np.sin(theta)) / theta ** 3 * K @ K


def view_noise(residuals: np.ndarray, J: np.ndarray, view_of_row: np.ndarray, camera_of_view: np.ndarray,
               prior_dof: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Corner noise std dev (px, per coordinate) of each view and each camera from a weighted least-squares
    fit (``J``: weighted Jacobian; ``residuals``: unweighted). Variance components: a view's RSS over its
    redundancy (its rows minus their hat-matrix trace), shrunk towards its camera's pooled value with
    ``prior_dof`` pseudo-observations so that a view with few corners cannot claim a tiny noise."""
    prior_dof = PRIOR_DOF if prior_dof is None else prior_dof
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1
    Js = J / scale
    leverage = np.einsum("ij,ij->i", Js @ np.linalg.pinv(Js.T @ Js), Js)
    n_views = len(camera_of_view)
    rss = np.bincount(view_of_row, residuals ** 2, n_views)
    redundancy = np.bincount(view_of_row, 1.0 - leverage, n_views)
    cameras = np.zeros(camera_of_view.max() + 1)
    for c in range(len(cameras)):
        mine = camera_of_view == c
        cameras[c] = np.sqrt(rss[mine].sum() / max(redundancy[mine].sum(), 1e-9))
    prior = cameras[camera_of_view] ** 2
    return np.sqrt((rss + prior_dof * prior) / (redundancy + prior_dof)), cameras


def frame_jackknife(J: np.ndarray, residuals: np.ndarray, frame_of_row: np.ndarray, n_shared: int,
                    n_frames: int) -> np.ndarray:
    """Delete-one-frame jackknife covariance of the first ``n_shared`` parameters, linearised: leaving frame f
    out (its rows and its 6 pose columns) moves them by N_f^-1 J_f^T r_f (one Gauss-Newton step, exact for a
    linear problem), N_f the normal matrix without it. ``J``, ``residuals``: weighted."""
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1
    Js = J / scale
    N = Js.T @ Js
    shifts = []
    for f in range(n_frames):
        rows = frame_of_row == f
        keep = np.ones(J.shape[1], bool)
        keep[n_shared + 6 * f:n_shared + 6 * f + 6] = False
        Jf = Js[rows][:, keep]
        step = np.linalg.solve(N[np.ix_(keep, keep)] - Jf.T @ Jf, Jf.T @ residuals[rows])
        shifts.append(step[:n_shared] / scale[:n_shared])
    d = np.array(shifts)
    d -= d.mean(0)
    return (len(d) - 1) / len(d) * d.T @ d


def _n_dist(cam: CameraCalibration) -> int:
    return 5 if cam.model == "FULL_OPENCV" else 4


def _intr(cam: CameraCalibration, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.ravel(dist)[: _n_dist(cam)]])


def _unpack_intr(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
    dist = np.zeros(5)
    dist[: len(p) - 4] = p[4:]
    return K, dist


def _float64(pair: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A view's (object points Nx3, image points Nx2) as contiguous float64 arrays."""
    obj, img = pair
    return np.ascontiguousarray(obj, np.float64).reshape(-1, 3), np.ascontiguousarray(img, np.float64).reshape(-1, 2)


def view_residuals(obj: np.ndarray, img: np.ndarray, intrinsics: np.ndarray, wide_from_board: np.ndarray,
                   narrow_from_wide: np.ndarray | None, with_jacobian: bool = True):
    """One view's reprojection errors (projected - detected, x0 y0 x1 ...: 2N) and their Jacobians with respect
    to the camera's ``intrinsics`` (fx, fy, cx, cy, distortion), the view's board pose ``wide_from_board`` (OpenCV
    rotation vector, translation) and, for the narrow camera, E^sl ``narrow_from_wide`` (likewise; None for the
    wide camera: its Jacobian is None too). Jacobians are None unless ``with_jacobian``."""
    K, dist = _unpack_intr(intrinsics)
    r, t = wide_from_board[:3], wide_from_board[3:]
    if narrow_from_wide is not None:  # narrow_from_board = E o wide_from_board
        r3, t3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            r, t, narrow_from_wide[:3], narrow_from_wide[3:])
        r, t = r3, t3
    proj, J = cv2.projectPoints(obj, r, t, K, dist)
    residual = (proj.reshape(-1, 2) - img).reshape(-1)
    if not with_jacobian:
        return residual, None, None, None
    d_intr = np.hstack([J[:, 6:10], J[:, 10:10 + len(intrinsics) - 4]])
    if narrow_from_wide is None:
        return residual, d_intr, J[:, :6], None
    A_r, A_t = J[:, :3], J[:, 3:6]
    d_pose = np.hstack([A_r @ dr3dr1 + A_t @ dt3dr1, A_r @ dr3dt1 + A_t @ dt3dt1])
    d_e = np.hstack([A_r @ dr3dr2 + A_t @ dt3dr2, A_r @ dr3dt2 + A_t @ dt3dt2])
    return residual, d_intr, d_pose, d_e


class _ViewCost(pyceres.CostFunction):
    """``weight * view_residuals``: parameter blocks the camera's intrinsics, the view's ``wide_from_board`` and,
    for the narrow camera, E^sl. ``weight`` (1 / the view's corner noise) may change between solves."""

    def __init__(self, obj: np.ndarray, img: np.ndarray, num_intrinsics: int, narrow: bool):
        super().__init__()
        self.obj, self.img, self.narrow, self.weight = obj, img, narrow, 1.0
        self.set_num_residuals(2 * len(obj))
        self.set_parameter_block_sizes([num_intrinsics, 6] + ([6] if narrow else []))

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - pyceres' name
        e = np.asarray(parameters[2]) if self.narrow else None
        residual, *derivatives = view_residuals(self.obj, self.img, np.asarray(parameters[0]),
                                                np.asarray(parameters[1]), e, jacobians is not None)
        residuals[:] = self.weight * residual
        if jacobians is not None:
            for out, d in zip(jacobians, derivatives):
                if out is not None:
                    out[:] = (self.weight * d).ravel()
        return True


class _JointProblem:
    """The joint refinement's Ceres problem over x = [wide intrinsics, narrow intrinsics, E^sl, board poses]
    (``joint_refine``'s layout, ``blocks`` its views), solved again with each set of per-view weights."""

    def __init__(self, x0: np.ndarray, blocks: list, ni_w: int, ni_n: int):
        off_e = ni_w + ni_n
        self.parts = [x0[:ni_w].copy(), x0[ni_w:off_e].copy(), x0[off_e:off_e + 6].copy()]
        poses = [x0[i:i + 6].copy() for i in range(off_e + 6, len(x0), 6)]
        self.parts += poses
        self.problem, self.costs = pyceres.Problem(), []
        for cam, i, _, obj, img in blocks:
            cost = _ViewCost(obj, img, ni_w if cam == 0 else ni_n, narrow=cam == 1)
            self.costs.append(cost)
            params = [self.parts[0], poses[i]] if cam == 0 else [self.parts[1], poses[i], self.parts[2]]
            self.problem.add_residual_block(cost, None, params)
        self.options = pyceres.SolverOptions()
        self.options.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR  # board poses eliminated
        self.options.function_tolerance = self.options.gradient_tolerance = 1e-14
        self.options.parameter_tolerance = 1e-14
        self.options.max_num_iterations = 500
        self.options.num_threads = 1
        self.options.logging_type = pyceres.LoggingType.SILENT

    def solve(self, view_weights: np.ndarray) -> tuple[np.ndarray, pyceres.SolverSummary]:
        """Minimise from the current estimate with these per-view weights; returns (x, Ceres' summary)."""
        for cost, weight in zip(self.costs, view_weights):
            cost.weight = float(weight)
        summary = pyceres.SolverSummary()
        pyceres.solve(self.options, self.problem, summary)
        return np.concatenate(self.parts), summary


def dense_residuals(x: np.ndarray, blocks: list, ni_w: int, ni_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted pixel residuals of every view in ``blocks`` ((camera, frame index, name, obj, img); camera 0
    wide, 1 narrow) at x = [wide intrinsics (``ni_w``), narrow intrinsics (``ni_n``), E^sl, board poses], and their
    dense Jacobian (for the noise levels, the covariance and the jackknife; the solver evaluates view by view)."""
    off_e = ni_w + ni_n
    off_f = off_e + 6
    out, jac, row = [], np.zeros((sum(2 * len(b[3]) for b in blocks), len(x))), 0
    for cam, i, _, obj, img in blocks:
        cols = slice(off_f + 6 * i, off_f + 6 * i + 6)
        intr_cols = slice(0, ni_w) if cam == 0 else slice(ni_w, off_e)
        residual, d_intr, d_pose, d_e = view_residuals(obj, img, x[intr_cols], x[cols],
                                                       x[off_e:off_f] if cam else None)
        out.append(residual)
        rows = slice(row, row + 2 * len(obj))
        jac[rows, cols] = d_pose
        jac[rows, intr_cols] = d_intr
        if cam == 1:
            jac[rows, off_e:off_f] = d_e
        row += 2 * len(obj)
    return np.concatenate(out), jac


def joint_refine(wide: CameraCalibration, narrow: CameraCalibration, narrow_pairs: dict, R: np.ndarray,
                 T: np.ndarray, common: list[str]) -> JointFit:
    """``narrow_pairs``: view -> (object, image) points of the narrow camera, in the orientation consistent
    with the wide camera (views whose narrow detection disagreed are simply left out)."""
    frames = sorted(set(wide.pairs) | set(narrow_pairs))
    ni_w, ni_n = 4 + _n_dist(wide), 4 + _n_dist(narrow)
    off_e = ni_w + ni_n
    off_f = off_e + 6
    x0 = np.concatenate([_intr(wide, wide.K, wide.dist), _intr(narrow, narrow.K, narrow.dist),
                         cv2.Rodrigues(R)[0].reshape(3), np.ravel(T)])
    poses = []
    for f in frames:
        if f in wide.poses:
            poses.append(np.concatenate(wide.poses[f]))
        else:  # seen by the narrow camera only: wide_from_board = E^-1 narrow_from_board
            Rn = cv2.Rodrigues(narrow.poses[f][0])[0]
            Rw = R.T @ Rn
            poses.append(np.concatenate([cv2.Rodrigues(Rw)[0].reshape(3), R.T @ (narrow.poses[f][1] - np.ravel(T))]))
    x0 = np.concatenate([x0, np.ravel(poses)])
    blocks = []  # (camera, frame index, name, obj, img)
    for i, f in enumerate(frames):
        if f in wide.pairs:
            blocks.append((0, i, f, *_float64(wide.pairs[f])))
        if f in narrow_pairs:
            blocks.append((1, i, f, *_float64(narrow_pairs[f])))

    view_of_row = np.repeat(np.arange(len(blocks)), [2 * len(b[3]) for b in blocks])
    camera_of_view = np.array([b[0] for b in blocks])
    # Corner noise differs between views by an order of magnitude (a frontal board against a steep tilt) and
    # between cameras (the narrow one sees bigger squares), so each view's residuals are weighted by
    # 1 / (its noise), estimated from the fit itself; refit until the noise levels settle.
    noise = np.where(camera_of_view == 0, wide.rms, narrow.rms) / np.sqrt(2) + 1e-3
    solver = _JointProblem(x0, blocks, ni_w, ni_n)
    for _ in range(NOISE_ITERATIONS):
        x, summary = solver.solve(1.0 / noise)
        weights = 1.0 / noise[view_of_row]
        previous = noise
        residuals, jacobian = dense_residuals(x, blocks, ni_w, ni_n)
        noise, camera_noise = view_noise(residuals, weights[:, None] * jacobian, view_of_row, camera_of_view)
        if np.all(np.abs(noise / previous - 1) < 0.02):
            break
    weights = 1.0 / noise[view_of_row]
    r = residuals.reshape(-1, 2)  # the last fit's unweighted pixel residuals from here on
    sq = np.sum(r ** 2, axis=1)
    # per block RMS
    start, per_block = 0, {}
    for cam, _, name, obj, _ in blocks:
        per_block[(cam, name)] = float(np.sqrt(sq[start:start + len(obj)].mean()))
        start += len(obj)
    cams = np.repeat([b[0] for b in blocks], [len(b[3]) for b in blocks])
    names = np.repeat([b[2] for b in blocks], [len(b[3]) for b in blocks])
    in_common = np.isin(names, common)
    J = weights[:, None] * jacobian
    dof = max(1, len(residuals) - len(x))
    sigma2 = float(np.sum((weights * residuals) ** 2)) / dof  # ~1 once the noise levels are right
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1
    JTJ = (J / scale).T @ (J / scale)
    condition = float(np.linalg.cond(JTJ))
    covariance = covariance_iid = None
    inflation = np.ones(3)
    try:
        cov = np.linalg.inv(JTJ) / np.outer(scale, scale) * sigma2
        std = np.sqrt(np.abs(np.diag(cov)))
        std = np.concatenate([std[0:4], std[ni_w:ni_w + 4]])
        # rotation vector r -> left perturbation w (R(r + dr) = Exp(J_l(r) dr) R(r)); board poses dropped
        A = np.eye(off_f)
        A[off_e:off_e + 3, off_e:off_e + 3] = left_jacobian(x[off_e:off_e + 3])
        covariance_iid = A @ cov[:off_f, :off_f] @ A.T
        frame_of_row = np.repeat([b[1] for b in blocks], [2 * len(b[3]) for b in blocks])
        jackknife = A @ frame_jackknife(J, weights * residuals, frame_of_row, off_f, len(frames)) @ A.T
        ratio = np.diag(jackknife) / np.diag(covariance_iid)
        parts = np.split(np.arange(off_f), [ni_w, off_e])  # wide intrinsics, narrow intrinsics, E^sl
        inflation = np.array([np.sqrt(max(1.0, float(np.median(ratio[p])))) for p in parts])
        k = np.concatenate([np.full(len(p), f) for p, f in zip(parts, inflation)])
        covariance = covariance_iid * np.outer(k, k)
    except np.linalg.LinAlgError:
        std = np.full(8, np.inf)
    Kw, dw = _unpack_intr(x[:ni_w])
    Kn, dn = _unpack_intr(x[ni_w:off_e])
    result = JointFit(K_wide=Kw, dist_wide=dw, K_narrow=Kn, dist_narrow=dn, R=cv2.Rodrigues(x[off_e:off_e + 3])[0],
                      T=x[off_e + 3:off_f].copy(), rms_wide=float(np.sqrt(sq[cams == 0].mean())),
                      rms_narrow=float(np.sqrt(sq[cams == 1].mean())) if np.any(cams == 1) else float("nan"),
                      rms_common=float(np.sqrt(sq[in_common].mean())) if in_common.any() else float("nan"),
                      per_view={n: (per_block.get((0, n), float("nan")), per_block.get((1, n), float("nan")))
                                for n in common},
                      std=std, condition=condition, covariance=covariance, n_wide=ni_w, n_narrow=ni_n,
                      noise=(float(camera_noise[0]), float(camera_noise[-1]) if len(camera_noise) > 1 else float("nan")),
                      covariance_iid=covariance_iid,
                      inflation=tuple(float(v) for v in inflation))  # type: ignore[arg-type]  # three parts
    logger.info("joint refinement: %d frames, RMS wide %.3f / narrow %.3f px, noise %.3f / %.3f px, sigma inflation "
                "%.2f / %.2f / %.2f, cond %.2g, %s", len(frames), result.rms_wide, result.rms_narrow, *result.noise,
                *inflation, condition, summary.message)
    return result
