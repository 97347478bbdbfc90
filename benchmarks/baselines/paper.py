"""The paper's own algorithm, as a baseline: pairwise two-view geometry chained round the rigs.

For each pair of adjacent rigs (in rigs.yaml order) on their wide images:
1. OpenCV SIFT; matches that pass Lowe's ratio test (0.8) in both directions and are mutual nearest
   neighbours; keypoints undistorted with the calibrated intrinsics (rigs.yaml).
2. Fundamental matrix: RANSAC whose hypotheses are OpenCV's normalised 8-point solution on 8 random
   matches, scored by MSAC (Sampson distance truncated at 1 px); each new best hypothesis is refitted
   with the 8-point algorithm on all its inliers while the cost decreases (LO-RANSAC; plain RANSAC
   with inlier counting kept ~60 % of the true inliers, or chose a plane-induced wrong F).
3. E = K2^T F K1; of its four decompositions, the one with the most inliers in front of both cameras
   (chirality); linear (DLT) triangulation of the inliers.
4. Two-view bundle adjustment (scipy ``least_squares``, Huber loss 1 px, |t| = 1 held as the gauge).
Chaining: the pairs' unit baselines are brought to one scale with the points they share: a keypoint of
rig i that is triangulated both by pair (i-1, i) and by pair (i, i+1) has two distances to rig i's
centre; the median ratio of those distances is the ratio of the two pairs' scales. The chain (rig 1's
wide camera = world) is then scaled to metres with scale.yaml's camera distance(s) (the rangefinder;
known lengths are not used), and each narrow pose is E^sl * wide pose. The chain stops at the first pair
without a usable relative pose or with fewer than ``MIN_SHARED`` shared points; later rigs stay
unregistered. On a full circle the closing pair (N, 1) is estimated only to report the loop-closure
rotation error.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from benchmarks.baselines.two_view import (
    normalised,
    pose_from_essential,
    ransac_fundamental,
    two_view_bundle_adjustment,
)
from rigsfm.core.conventions import opencv_from_colmap_pixels, rotation_angle_deg
from rigsfm.core.image_files import read_image
from rigsfm.core.rig import RigCalibration, add_posed_rig
from rigsfm.run.pipeline import load_inputs

logger = logging.getLogger(__name__)

RATIO = 0.8
MIN_INLIERS = 30
MIN_SHARED = 5
MAX_FEATURES = 8192


@dataclass
class Features:
    keypoints: np.ndarray  # (N, 2) undistorted pixels, OpenCV convention
    descriptors: np.ndarray
    K: np.ndarray  # OpenCV-convention intrinsic matrix of the undistorted pixels


@dataclass
class PairResult:
    first: str
    second: str
    matches: int = 0
    inliers: int = 0
    second_from_first: pycolmap.Rigid3d | None = None  # |t| = 1
    points: dict[int, np.ndarray] = field(default_factory=dict)  # first's keypoint -> xyz in first's frame
    second_keypoint: dict[int, int] = field(default_factory=dict)  # first's keypoint -> second's keypoint
    ba_rms_px: float | None = None


def opencv_intrinsics(camera: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """K (OpenCV pixel convention) and distortion of an OPENCV / PINHOLE camera."""
    fx, fy, cx, cy = camera.params[:4]
    cx, cy = opencv_from_colmap_pixels([cx, cy])
    distortion = np.asarray(camera.params[4:8] if camera.model.name == "OPENCV" else np.zeros(4), dtype=np.float64)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), distortion


def detect(path: Path, camera: pycolmap.Camera) -> Features:
    gray = read_image(path, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise OSError(f"cannot read {path}")
    keypoints, descriptors = cv2.SIFT_create(nfeatures=MAX_FEATURES).detectAndCompute(gray, None)
    K, distortion = opencv_intrinsics(camera)
    xy = np.array([kp.pt for kp in keypoints], dtype=np.float64).reshape(-1, 1, 2)
    undistorted = cv2.undistortPoints(xy, K, distortion, P=K).reshape(-1, 2) if len(xy) else xy.reshape(0, 2)
    return Features(undistorted, descriptors, K)


def mutual_ratio_matches(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """(M, 2) index pairs that pass the ratio test both ways and are mutual nearest neighbours."""
    if d1 is None or d2 is None or len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), dtype=int)
    matcher = cv2.BFMatcher(cv2.NORM_L2)

    def best(a, b) -> dict[int, int]:
        return {m.queryIdx: m.trainIdx for m, n in matcher.knnMatch(a, b, k=2) if m.distance < RATIO * n.distance}

    forward, backward = best(d1, d2), best(d2, d1)
    return np.array([(i, j) for i, j in forward.items() if backward.get(j) == i], dtype=int).reshape(-1, 2)


def estimate_pair(a: str, b: str, fa: Features, fb: Features, timings: dict) -> PairResult:
    result = PairResult(a, b)
    start = time.perf_counter()
    matches = mutual_ratio_matches(fa.descriptors, fb.descriptors)
    timings["matching"] += time.perf_counter() - start
    result.matches = len(matches)
    if len(matches) < MIN_INLIERS:
        return result
    start = time.perf_counter()
    u1, u2 = fa.keypoints[matches[:, 0]], fb.keypoints[matches[:, 1]]
    F, inliers = ransac_fundamental(u1, u2, np.random.default_rng(0))
    if F is None or inliers.sum() < MIN_INLIERS:
        timings["two_view"] += time.perf_counter() - start
        return result
    E = fb.K.T @ F @ fa.K
    x1, x2 = normalised(u1[inliers], fa.K), normalised(u2[inliers], fb.K)
    R, t, X, front = pose_from_essential(E, x1, x2)
    keep = np.flatnonzero(inliers)[front]
    timings["two_view"] += time.perf_counter() - start
    if len(keep) < MIN_INLIERS:
        return result
    start = time.perf_counter()
    R, t, X, rms = two_view_bundle_adjustment(R, t, X[front], u1[keep], u2[keep], fa.K, fb.K)
    timings["bundle_adjustment"] += time.perf_counter() - start
    in_front = (X[:, 2] > 0) & ((X @ R.T + t)[:, 2] > 0)
    result.inliers, result.ba_rms_px = int(in_front.sum()), rms
    result.second_from_first = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
    for k, xyz, ok in zip(keep, X, in_front):
        if ok:
            result.points[int(matches[k, 0])] = xyz
            result.second_keypoint[int(matches[k, 0])] = int(matches[k, 1])
    return result


def relative_scale(previous: PairResult, current: PairResult) -> tuple[float | None, int]:
    """Scale of ``current`` (in units of ``previous``) from the points both triangulate in their shared rig."""
    in_shared = {previous.second_keypoint[k]: previous.second_from_first * xyz for k, xyz in previous.points.items()}
    ratios = [np.linalg.norm(in_shared[k]) / np.linalg.norm(xyz) for k, xyz in current.points.items() if k in in_shared]
    if len(ratios) < MIN_SHARED:
        return None, len(ratios)
    return float(np.median(ratios)), len(ratios)


def reconstruction_from_poses(rigs: list[RigCalibration], wide_from_world: dict[str, pycolmap.Rigid3d],
                              frame_file: str) -> pycolmap.Reconstruction:
    """A reconstruction with one rig (wide = reference, narrow at E^sl) per registered rig."""
    rec = pycolmap.Reconstruction()
    for index, rig_cal in enumerate(rigs):
        if rig_cal.name in wide_from_world:
            frame = {sensor: f"{rig_cal.name}/{sensor}/{frame_file}" for sensor in ("wide", "narrow")}
            add_posed_rig(rec, index + 1, rig_cal, wide_from_world[rig_cal.name], [frame])
    return rec


def metric_factor(spec, centres: dict[str, np.ndarray]) -> float | None:
    """Metres per chain unit from scale.yaml's camera distances between registered wide cameras."""
    factors = []
    for d in spec.camera_distances if spec else ():
        a, b = d.a.split("/")[0], d.b.split("/")[0]
        if a in centres and b in centres and d.a.endswith("/wide") and d.b.endswith("/wide"):
            factors.append(d.meters / np.linalg.norm(centres[a] - centres[b]))
    return float(np.mean(factors)) if factors else None


def run_paper(scene_root: Path) -> tuple[pycolmap.Reconstruction, dict]:
    """Run the baseline on a rendered scene folder (images/, rigs.yaml, scale.yaml); returns the
    reconstruction (registered rigs only, metres if scaled) and a report with per-stage timings."""
    scene_root = Path(scene_root)
    inputs = load_inputs(scene_root / "images", scene_root / "rigs.yaml", scene_root / "scale.yaml")
    timings = {"features": 0.0, "matching": 0.0, "two_view": 0.0, "bundle_adjustment": 0.0, "chaining": 0.0}
    wide = {e.rig: e for e in inputs.images if e.sensor == "wide"}
    frame_file = min(wide.values(), key=lambda e: e.frame).frame
    wide = {e.rig: e for e in inputs.images if e.sensor == "wide" and e.frame == frame_file}
    order = [r for r in inputs.rigs if r.name in wide]
    start = time.perf_counter()
    features = {r.name: detect(wide[r.name].path, r.wide) for r in order}
    timings["features"] = time.perf_counter() - start

    pairs: list[PairResult] = []
    wide_from_world = {order[0].name: pycolmap.Rigid3d()}
    scale, stopped = 1.0, None
    for a, b in itertools.pairwise(order):
        pair = estimate_pair(a.name, b.name, features[a.name], features[b.name], timings)
        pairs.append(pair)
        if pair.second_from_first is None:
            stopped = f"pair {a.name}-{b.name}: no relative pose ({pair.matches} matches, {pair.inliers} inliers)"
            break
        t0 = time.perf_counter()
        if len(pairs) > 1:
            ratio, shared = relative_scale(pairs[-2], pair)
            if ratio is None:
                stopped = f"pair {a.name}-{b.name}: only {shared} points shared with the previous pair"
                break
            scale *= ratio
        step = pycolmap.Rigid3d(pair.second_from_first.rotation, scale * pair.second_from_first.translation)
        wide_from_world[b.name] = step * wide_from_world[a.name]
        timings["chaining"] += time.perf_counter() - t0
    loop_closure_deg = None
    full_circle = len(order) > 2 and stopped is None and _is_full_circle(scene_root)
    if full_circle:
        closing = estimate_pair(order[-1].name, order[0].name, features[order[-1].name], features[order[0].name],
                                {"matching": 0.0, "two_view": 0.0, "bundle_adjustment": 0.0})
        if closing.second_from_first is not None:
            chained = wide_from_world[order[0].name] * wide_from_world[order[-1].name].inverse()
            loop_closure_deg = rotation_angle_deg(chained.rotation.matrix(),
                                                  closing.second_from_first.rotation.matrix())
    t0 = time.perf_counter()
    centres = {name: np.asarray(pose.inverse().translation) for name, pose in wide_from_world.items()}
    factor = metric_factor(inputs.scale, centres)
    if factor is not None:
        wide_from_world = {n: pycolmap.Rigid3d(p.rotation, factor * p.translation) for n, p in wide_from_world.items()}
    rec = reconstruction_from_poses(inputs.rigs, wide_from_world, frame_file)
    timings["chaining"] += time.perf_counter() - t0
    if stopped:
        logger.warning("paper baseline: chain stopped at %s", stopped)
    report = {
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "metric": factor is not None,
        "stopped": stopped,
        "loop_closure_rotation_deg": loop_closure_deg,
        "pairs": [{"first": p.first, "second": p.second, "matches": p.matches, "inliers": p.inliers,
                   "ba_rms_px": p.ba_rms_px} for p in pairs],
    }
    return rec, report


def _is_full_circle(scene_root: Path) -> bool:
    import yaml

    scene = scene_root / "scene.yaml"
    if not scene.exists():
        return False
    return float(yaml.safe_load(scene.read_text())["options"].get("arc_deg", 0.0)) >= 360.0
