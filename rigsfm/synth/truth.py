"""Accuracy against ground truth, and the oracle: the fixed-calibration reference.

The oracle is bundle adjustment started from the ground-truth poses with the *same* observations
(tracks) and the *same* calibration file as the run, intrinsics and E^sl held fixed (``--fixed-calibration``
whatever the options say): the best a pipeline that trusts the calibration file can do given the image noise
and the calibration errors. The default adjustment, which refines the calibration, can beat it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import pycolmap

from rigsfm.core.conventions import rotation_angle_deg
from rigsfm.core.names import name_of
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.adjust import AdjustOptions, adjust, restore_calibration
from rigsfm.run.adjustment.scale import triangulate_in_images
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.options import Calibration


def _posed(reconstruction: pycolmap.Reconstruction, sensor: str) -> dict[str, pycolmap.Image]:
    return {
        im.name: im for im in reconstruction.images.values() if im.has_pose and name_of(im).sensor == sensor
    }


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    cos = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _stats(values) -> dict:
    v = np.abs(np.asarray(values, dtype=np.float64))
    return {"median": float(np.median(v)), "max": float(v.max())} if v.size else {"median": None, "max": None}


def centre_errors_mm(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    """Narrow centre errors after a similarity alignment of the *wide* centres onto the truth.

    A scale trap (E^sl scaled with the world) shows here as narrow centres off by the scaled baseline.
    """
    est_wide, gt_wide = _posed(estimate, "wide"), _posed(truth, "wide")
    names = sorted(set(est_wide) & set(gt_wide))
    if len(names) < 3:  # a similarity needs three non-collinear centres: fall back to none
        return {"median": None, "max": None}
    gt_from_est = pycolmap.estimate_sim3d(
        np.array([est_wide[n].projection_center() for n in names]),
        np.array([gt_wide[n].projection_center() for n in names]),
    )
    est, gt = _posed(estimate, "narrow"), _posed(truth, "narrow")
    errors = [
        1000.0 * np.linalg.norm(gt_from_est * est[n].projection_center()  # type: ignore[operator]  # posed centres
                                - gt[n].projection_center())
        for n in sorted(set(est) & set(gt))
    ]
    return _stats(errors)


def compare_to_ground_truth(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction,
                            sensor: str = "narrow") -> dict:
    """Gauge-free errors of one sensor's cameras: pairwise relative rotation, translation direction,
    centre distance (metric), plus the registration rate."""
    est, gt = _posed(estimate, sensor), _posed(truth, sensor)
    names = sorted(set(est) & set(gt))
    rot, direction, distance = [], [], []
    for i, j in itertools.combinations(names, 2):
        e = est[j].cam_from_world() * est[i].cam_from_world().inverse()
        g = gt[j].cam_from_world() * gt[i].cam_from_world().inverse()
        rot.append(rotation_angle_deg(e.rotation.matrix(), g.rotation.matrix()))
        direction.append(_angle_between(e.translation, g.translation))
        g_dist = np.linalg.norm(g.translation)
        distance.append(100.0 * (np.linalg.norm(e.translation) - g_dist) / g_dist)

    return {
        "registered": len(names),
        "total": len(gt),
        "pairs": len(rot),
        "relative_rotation_deg": _stats(rot),
        "translation_direction_deg": _stats(direction),
        "distance_error_percent": _stats(distance),
    }


def wide_distance_error_percent(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, a: str,
                                b: str) -> float:
    """Metric error of the distance between two cameras (e.g. the rangefinder pair), in percent."""
    def dist(rec: pycolmap.Reconstruction) -> float:
        return float(np.linalg.norm(rec.find_image_with_name(a).projection_center()
                                    - rec.find_image_with_name(b).projection_center()))

    return 100.0 * (dist(estimate) - dist(truth)) / dist(truth)


def oracle(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, rigs: Sequence[RigCalibration],
           scale_spec: ScaleSpec | None = None, options: AdjustOptions | None = None) -> pycolmap.Reconstruction:
    """The fixed-calibration stage started from ground-truth poses, with the estimate's observations, the
    same calibration file and the same scale measurements."""
    rec = pycolmap.Reconstruction(estimate)
    for frame_id in rec.reg_frame_ids():
        frame = rec.frame(frame_id)
        ref_image = next(rec.image(d.id) for d in frame.image_ids if rec.image(d.id).is_ref_in_frame())
        truth_image = truth.find_image_with_name(ref_image.name)
        frame.rig_from_world = truth.frame(truth_image.frame_id).rig_from_world
    restore_calibration(rec, rigs)
    for point3D_id in list(rec.point3D_ids()):
        point = rec.points3D[point3D_id]
        observations = [(rec.images[e.image_id], rec.images[e.image_id].points2D[e.point2D_idx].xy)
                        for e in point.track.elements]
        xyz = triangulate_in_images(rec, observations)
        if xyz is None:
            rec.delete_point3D(point3D_id)
        else:
            point.xyz = xyz
    return adjust(rec, rigs, scale_spec, replace(options or AdjustOptions(), calibration=Calibration.FIXED)).reconstruction
