"""E^sl rotation and translation direction from a textured scene seen by both cameras of a rig.

The narrow camera has ~4x the focal length of the wide one, so the same surface patch appears ~4x larger
in it. SIFT is scale invariant only within its octave range and wastes most narrow features on detail the
wide camera cannot see, so the narrow image is first downscaled by ``f_wide / f_narrow`` (area filter):
both images then show the scene at about the same scale. Keypoints are mapped back to full-resolution
narrow pixels. Matches (Lowe ratio test + mutual best match) are pooled over all frames (the rig is rigid,
so one E holds for all), undistorted to normalised coordinates, and fed to a RANSAC essential matrix and
``recoverPose``; the pose is then refined by robust least squares on the Sampson error of the inliers.
The translation comes out as a unit direction; its length is taken from the board or ``--baseline``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from rigsfm.calibrate.board import read_gray
from rigsfm.core.conventions import opencv_from_resized_pixels
from rigsfm.core.errors import ReconstructionError
from rigsfm.core.geometry import sampson, skew
from rigsfm.core.sift import detect, opencv_sift

logger = logging.getLogger(__name__)

RATIO = 0.8
MIN_INLIERS = 30
RANSAC_PX = 1.0  # threshold in wide-camera pixels
MAX_FEATURES = 20000


@dataclass
class SceneEstimate:
    R: np.ndarray  # narrow_from_wide rotation
    direction: np.ndarray  # unit translation direction (narrow_from_wide)
    matches: int
    inliers: int
    rms_px: float  # RMS Sampson error of the inliers, wide pixels
    scale: float  # narrow downscale factor used for matching


def _sift(gray: np.ndarray, sift) -> tuple[np.ndarray, np.ndarray]:
    xy, descriptors = detect(sift, gray)
    if descriptors is None:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    return xy, descriptors


def mutual_ratio_matches(d1: np.ndarray, d2: np.ndarray, ratio: float = RATIO) -> np.ndarray:
    """(M, 2) index pairs passing Lowe's ratio test in both directions and being mutual best matches."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), int)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(d1, d2, k=2)
    backward = matcher.knnMatch(d2, d1, k=2)
    best_back = {m[0].queryIdx: m[0].trainIdx for m in backward if len(m) == 2 and m[0].distance < ratio * m[1].distance}
    return np.array([(m[0].queryIdx, m[0].trainIdx) for m in forward
                     if len(m) == 2 and m[0].distance < ratio * m[1].distance
                     and best_back.get(m[0].trainIdx) == m[0].queryIdx], int).reshape(-1, 2)


def _normalise(points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    return cv2.undistortPoints(points.reshape(-1, 1, 2), K, dist, criteria=criteria).reshape(-1, 2)


def _refine(R0: np.ndarray, t0: np.ndarray, x1: np.ndarray, x2: np.ndarray, scale: float):
    """Minimise the Sampson error over the rotation (3) and the unit translation direction (2)."""
    t0 = t0 / np.linalg.norm(t0)
    b1 = np.cross(t0, [1.0, 0, 0] if abs(t0[0]) < 0.9 else [0, 1.0, 0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(t0, b1)

    def unpack(p):
        R = cv2.Rodrigues(p[:3])[0] @ R0
        t = t0 + p[3] * b1 + p[4] * b2
        return R, t / np.linalg.norm(t)

    def residuals(p):
        R, t = unpack(p)
        return scale * sampson(skew(t) @ R, x1, x2)

    fit = least_squares(residuals, np.zeros(5), loss="huber", f_scale=RANSAC_PX, x_scale=1e-3)
    return unpack(fit.x)


def estimate_from_scene(frames: list[tuple[Path, Path]], K_wide: np.ndarray, dist_wide: np.ndarray,
                        K_narrow: np.ndarray, dist_narrow: np.ndarray, where: str) -> SceneEstimate:
    """narrow_from_wide rotation and translation direction from synchronised (wide, narrow) scene images."""
    scale = float(np.clip(K_wide[0, 0] / K_narrow[0, 0], 0.05, 1.0))
    sift = opencv_sift(MAX_FEATURES)
    pts_w, pts_n = [], []
    for wide_path, narrow_path in frames:
        kw, dw = _sift(read_gray(wide_path), sift)
        narrow = read_gray(narrow_path)
        small = cv2.resize(narrow, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else narrow
        kn, dn = _sift(small, sift)
        kn = opencv_from_resized_pixels(kn, 1 / scale)  # full-resolution narrow pixels
        m = mutual_ratio_matches(dw, dn)
        pts_w.append(kw[m[:, 0]] if len(m) else np.zeros((0, 2)))
        pts_n.append(kn[m[:, 1]] if len(m) else np.zeros((0, 2)))
        logger.info("%s: %s: %d wide / %d narrow features, %d mutual matches", where, wide_path.name, len(kw), len(kn), len(m))
    pw, pn = np.vstack(pts_w), np.vstack(pts_n)
    if len(pw) < MIN_INLIERS:
        raise ReconstructionError(f"{where}: only {len(pw)} SIFT matches between the wide and narrow scene images "
                                  f"(need {MIN_INLIERS}+); use a scene with more texture inside the narrow view")
    x1, x2 = _normalise(pw, K_wide, dist_wide), _normalise(pn, K_narrow, dist_narrow)
    f = float(K_wide[0, 0])
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=RANSAC_PX / f,
                                   maxIters=5000)
    if E is None or E.shape != (3, 3):
        raise ReconstructionError(f"{where}: no essential matrix fits the {len(pw)} scene matches; the scene "
                                  "may be too flat or too distant, or the matches wrong")
    _inliers, R, t, mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask)
    keep = mask.reshape(-1) > 0
    if keep.sum() < MIN_INLIERS:
        raise ReconstructionError(f"{where}: only {int(keep.sum())} of {len(pw)} scene matches agree on one relative "
                                  f"pose (need {MIN_INLIERS}); use a scene with more texture and depth")
    R, direction = _refine(R, t.reshape(3), x1[keep], x2[keep], f)
    errors = f * sampson(skew(direction) @ R, x1, x2)
    keep = np.abs(errors) < 3 * RANSAC_PX
    rms = float(np.sqrt(np.mean(errors[keep] ** 2)))
    logger.info("%s: scene E^sl from %d inliers of %d matches, RMS %.2f px", where, keep.sum(), len(pw), rms)
    return SceneEstimate(R=R, direction=direction, matches=len(pw), inliers=int(keep.sum()), rms_px=rms, scale=scale)
