"""Two-view geometry of the paper baseline: F by RANSAC over normalised 8-point hypotheses, E and its
chirality-checked decomposition, linear triangulation, two-view bundle adjustment (scipy)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

SAMPSON_THRESHOLD_PX = 1.0


def sampson_px(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    h1, h2 = np.c_[p1, np.ones(len(p1))], np.c_[p2, np.ones(len(p2))]
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    numerator = np.sum(h2 * Fx1, axis=1) ** 2
    return np.sqrt(numerator / (Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2))


def msac_cost(errors: np.ndarray) -> float:
    return float(np.sum(np.minimum(errors, SAMPSON_THRESHOLD_PX) ** 2))


def refit_fundamental(p1: np.ndarray, p2: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Normalised 8-point on all inliers, repeated while the MSAC cost decreases."""
    cost = msac_cost(sampson_px(F, p1, p2))
    for _ in range(10):
        inliers = sampson_px(F, p1, p2) < SAMPSON_THRESHOLD_PX
        if inliers.sum() < 8:
            break
        candidate, _ = cv2.findFundamentalMat(p1[inliers], p2[inliers], cv2.FM_8POINT)
        if candidate is None or candidate.shape != (3, 3):
            break
        candidate_cost = msac_cost(sampson_px(candidate, p1, p2))
        if candidate_cost >= cost - 1e-9:
            break
        F, cost = candidate, candidate_cost
    return F


def ransac_fundamental(p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator,
                       min_iterations: int = 1000, max_iterations: int = 5000,
                       confidence: float = 0.999) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC over normalised 8-point hypotheses (8 random matches), scored by the MSAC cost (truncated
    squared Sampson distance); every new best hypothesis is refitted on its inliers (local optimisation).
    At least ``min_iterations``: with a dominant ground plane, samples of planar points give a wrong F
    that still explains most matches, and the adaptive count alone stops before a better one is drawn."""
    best_F, best_cost = None, np.inf
    needed, iteration = max_iterations, 0
    while iteration < min(needed, max_iterations):
        iteration += 1
        sample = rng.choice(len(p1), 8, replace=False)
        F, _ = cv2.findFundamentalMat(p1[sample], p2[sample], cv2.FM_8POINT)
        if F is None or F.shape != (3, 3):
            continue
        if msac_cost(sampson_px(F, p1, p2)) < best_cost:
            F = refit_fundamental(p1, p2, F)
            best_F, best_cost = F, msac_cost(sampson_px(F, p1, p2))
            ratio = float(np.mean(sampson_px(F, p1, p2) < SAMPSON_THRESHOLD_PX))
            needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1e-12, 1 - ratio**8)))) if ratio < 1 else 0
            needed = max(needed, min_iterations)
    if best_F is None:
        return None, np.zeros(len(p1), dtype=bool)
    return best_F, sampson_px(best_F, p1, p2) < SAMPSON_THRESHOLD_PX


def normalised(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (points - K[:2, 2]) / np.diag(K)[:2]


def triangulate(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation in normalised coordinates; points in the first camera's frame."""
    h = cv2.triangulatePoints(np.eye(3, 4), np.c_[R, t], x1.T.astype(np.float64), x2.T.astype(np.float64))
    return (h[:3] / h[3]).T


def pose_from_essential(E: np.ndarray, x1: np.ndarray, x2: np.ndarray):
    """The decomposition of E with the most points in front of both cameras; and those points."""
    R1, R2, t = cv2.decomposeEssentialMat(E)
    best = None
    for R, tt in ((R1, t), (R1, -t), (R2, t), (R2, -t)):
        X = triangulate(R, tt.ravel(), x1, x2)
        front = (X[:, 2] > 0) & ((X @ R.T + tt.ravel())[:, 2] > 0)
        if best is None or front.sum() > best[3].sum():
            best = (R, tt.ravel(), X, front)
    return best


def two_view_bundle_adjustment(R, t, X, u1, u2, K1, K2):
    """Refine the second camera's pose and the points; first camera fixed, |t| = 1 as the gauge."""
    n = len(X)

    def project(K, Xc):
        return (Xc[:, :2] / Xc[:, 2:3]) * np.diag(K)[:2] + K[:2, 2]

    def residuals(x):
        Rx = cv2.Rodrigues(x[:3])[0]
        P = x[6:].reshape(n, 3)
        r1 = project(K1, P) - u1
        r2 = project(K2, P @ Rx.T + x[3:6]) - u2
        return np.concatenate([r1.ravel(), r2.ravel(), [1e3 * (np.linalg.norm(x[3:6]) - 1.0)]])

    sparsity = lil_matrix((4 * n + 1, 6 + 3 * n), dtype=int)
    idx = np.arange(n)
    for k in range(3):
        for row0 in (0, 1):
            sparsity[2 * idx + row0, 6 + 3 * idx + k] = 1
            sparsity[2 * n + 2 * idx + row0, 6 + 3 * idx + k] = 1
    sparsity[2 * n :, :6] = 1
    x0 = np.concatenate([cv2.Rodrigues(R)[0].ravel(), t / np.linalg.norm(t), X.ravel()])
    result = least_squares(residuals, x0, jac_sparsity=sparsity, loss="huber", f_scale=1.0, x_scale="jac",
                           method="trf", max_nfev=200)
    x = result.x
    rms = float(np.sqrt(np.mean(result.fun[:-1] ** 2)))
    return cv2.Rodrigues(x[:3])[0], x[3:6], x[6:].reshape(n, 3), rms
