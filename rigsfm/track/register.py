"""Register one synchronised frame of one rig against the reference map (the per-frame work).

:func:`register_frame` is a plain function of picklable inputs (a :class:`FrameTask` and the
:class:`~rigsfm.track.reference.ReferenceMap`) returning a JSON-ready dict, so any executor can run
it. Steps: SIFT on each image of the frame (pycolmap, the options of ``rigsfm run``), 2D-3D matching
against the descriptors of the map points (Lowe ratio test + mutual nearest neighbour, per reference
image), then the rig pose with E^sl held fixed (:func:`~rigsfm.track.pose.estimate_rig_pose`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from rigsfm.core.image_files import decode_image, read_image
from rigsfm.run.inputs.images import unreadable_image
from rigsfm.track.options import RegistrationOptions
from rigsfm.track.pose import estimate_rig_pose, pose_covariance, reprojection_errors
from rigsfm.track.reference import ReferenceMap, ReferenceRig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameTask:
    """One frame of one rig; ``images`` maps sensor -> file path or the encoded file's bytes."""

    rig: str
    frame: str
    images: dict[str, Path | bytes] = field(default_factory=dict)


_EXTRACTORS: dict[int, object] = {}


def _extractor(max_num_features: int):
    if max_num_features not in _EXTRACTORS:
        options = pycolmap.FeatureExtractionOptions(num_threads=1, use_gpu=False)
        options.sift.max_num_features = max_num_features
        _EXTRACTORS[max_num_features] = pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)
    return _EXTRACTORS[max_num_features]


def read_grey(source: Path | bytes) -> np.ndarray | None:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return decode_image(source, cv2.IMREAD_GRAYSCALE)
    return read_image(source, cv2.IMREAD_GRAYSCALE)


def extract_sift(image: np.ndarray, max_num_features: int) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint positions (N x 2, COLMAP pixels) and uint8 descriptors (N x 128), as in database.db."""
    keypoints, descriptors = _extractor(max_num_features).extract_from_uint8_array(np.ascontiguousarray(image))
    xy = np.array([[k.x, k.y] for k in keypoints], dtype=np.float64).reshape(-1, 2)
    return xy, np.asarray(descriptors.data, dtype=np.uint8).reshape(-1, 128)


def match_mutual_ratio(query: np.ndarray, train: np.ndarray, max_ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (query, train) and L2 distances of matches passing the ratio test and the mutual check.

    SIFT's uint8 descriptors make every squared distance an integer below 2**24, exact in float32 whatever the
    order of summation: the table is computed in blocks of rows, once each way (a row's minimum is fast, a
    column's is not), and the blocks agree exactly with each other."""
    if len(query) < 2 or len(train) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    q, t = query.astype(np.float32), train.astype(np.float32)
    best, first, second = _two_nearest(q, t)
    best_query_of_train, _, _ = _two_nearest(t, q)
    rows = np.arange(len(q))
    keep = (best_query_of_train[best] == rows) & (np.sqrt(first) < max_ratio * np.sqrt(second))
    return rows[keep].astype(np.int64), best[keep].astype(np.int64), np.sqrt(first[keep]).astype(np.float64)


MATCH_BLOCK_ROWS = 2048  # rows of the distance table at a time (64 MB against 8 192 descriptors)


def _two_nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of ``a``: the index of its nearest row of ``b`` (the first of ties) and the squared distances
    to the nearest and the second nearest. The table holds ``|b|^2 - 2 a.b`` (a row's ``|a|^2`` moves no
    minimum; added to the two kept), built in place: faster than the whole ``|a - b|^2`` table, and as exact (integers below 2**24, see :func:`match_mutual_ratio`)."""
    norms_b = (b * b).sum(1)
    best = np.empty(len(a), np.int64)
    first, second = np.empty(len(a), np.float32), np.empty(len(a), np.float32)
    for start in range(0, len(a), MATCH_BLOCK_ROWS):
        block = a[start:start + MATCH_BLOCK_ROWS]
        table = block @ b.T
        table *= -2.0
        table += norms_b
        norms = (block * block).sum(1)
        rows = np.arange(len(block))
        nearest = np.argmin(table, axis=1)
        best[start:start + len(block)] = nearest
        first[start:start + len(block)] = np.maximum(table[rows, nearest] + norms, 0.0)
        table[rows, nearest] = np.inf
        second[start:start + len(block)] = np.maximum(table.min(axis=1) + norms, 0.0)
    return best, first, second


def match_to_map(descriptors: np.ndarray, reference: ReferenceMap, rig: ReferenceRig,
                 max_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(query keypoint indices, 3D points) matched against the rig's reference images; one 3D point per
    keypoint (the closest descriptor when several reference images match it)."""
    found = [(*match_mutual_ratio(descriptors, reference.blocks[b].descriptors, max_ratio), b) for b in rig.blocks]
    query = np.concatenate([f[0] for f in found])
    distance = np.concatenate([f[2] for f in found])
    xyz = np.concatenate([reference.blocks[b].xyz[t] for _, t, _, b in found]).reshape(-1, 3)
    order = np.lexsort((distance, query))
    first = order[np.r_[True, np.diff(query[order]) != 0]] if len(order) else order
    return query[first], xyz[first]


def _sensors_to_use(task: FrameTask, rig: ReferenceRig, options: RegistrationOptions) -> list[str]:
    use_narrow = rig.narrow_observes_map if options.use_narrow is None else options.use_narrow
    wanted = ["wide", "narrow"] if use_narrow and rig.narrow is not None else ["wide"]
    return [s for s in wanted if s in task.images]


def register_frame(task: FrameTask, reference: ReferenceMap, options: RegistrationOptions | None = None) -> dict:
    """Register one frame; returns a JSON-ready record with status ``registered``, ``failed`` (too few
    matches/inliers: a result, not an error) or ``bad_input`` (the image cannot be used; ``reason`` says why)."""
    options = options or RegistrationOptions()
    start = time.perf_counter()
    record: dict[str, Any] = {"rig": task.rig, "frame": task.frame, "status": "failed", "reason": None, "sensors": {}}
    rig = reference.rigs[task.rig]
    cameras, sensor_from_rig = rig.cameras()
    correspondences = {}
    for sensor in _sensors_to_use(task, rig, options):
        source = task.images[sensor]
        image = read_grey(source)
        camera = cameras[sensor]
        if image is None:  # a file shipped as bytes is named by its place in NEW_IMAGES
            return {**record, "status": "bad_input", "reason": unreadable_image(
                source if isinstance(source, (str, Path)) else f"{task.rig}/{sensor}/{task.frame}")}
        if image.shape != (camera.height, camera.width):
            return {**record, "status": "bad_input",
                    "reason": f"{task.rig}/{sensor}/{task.frame} is {image.shape[1]}x{image.shape[0]}; the {sensor} "
                              f"camera of {task.rig} is calibrated for {camera.width}x{camera.height}"}
        xy, descriptors = extract_sift(image, options.max_num_features)
        keypoints, xyz = match_to_map(descriptors, reference, rig, options.max_ratio)
        correspondences[sensor] = (xy[keypoints], xyz)
        record["sensors"][sensor] = {"features": len(xy), "matches": len(keypoints)}
    estimate = estimate_rig_pose(correspondences, cameras, sensor_from_rig, options)
    if estimate is None:
        record["reason"] = f"fewer than {options.min_matches} 2D-3D matches, or RANSAC found no pose"
    else:
        wide_from_world, inliers, used = estimate
        per_sensor_errors: list[np.ndarray] = []
        observations, offset = [], 0
        for sensor in used:
            xy, xyz = correspondences[sensor]
            mask = inliers[offset:offset + len(xy)]
            offset += len(xy)
            record["sensors"][sensor]["inliers"] = int(mask.sum())
            per_sensor_errors.append(reprojection_errors(sensor_from_rig[sensor] * wide_from_world, cameras[sensor],
                                                         xy[mask], xyz[mask]))
            observations.append((cameras[sensor], sensor_from_rig[sensor], xy[mask], xyz[mask]))
        errors = np.concatenate(per_sensor_errors)
        record.update(num_inliers=int(inliers.sum()), used_sensors=used,
                      reprojection_error_px=float(errors.mean()) if errors.size else None)
        if inliers.sum() < options.min_inliers:
            record["reason"] = f"only {int(inliers.sum())} inliers (need {options.min_inliers})"
        else:
            covariance = pose_covariance(wide_from_world, observations, rig.baseline_wide_from_world.rotation.matrix())
            record.update(status="registered", wide_from_world=wide_from_world.matrix().tolist(),
                          covariance=covariance.tolist())
    record["time_s"] = round(time.perf_counter() - start, 3)
    return record
