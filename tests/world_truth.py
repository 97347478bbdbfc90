"""The analyst's world of a finished run against a rendered scene's exact ground truth (the synthetic floor is
z = 0 of the truth's world).

Only gauge-free quantities: camera heights above the run's floor (z in OUT/sparse) against the true heights; the
angle between the floor normal and the truth's up, seen from each camera (the normal in camera coordinates) and
after a similarity alignment of all camera centres; distances between true plane points mapped through each
narrow camera's delivered ``ground_from_image`` (true pixels of the exact camera, undistorted with the run's
camera model) against their true distances; and, for the epipolar self-check, the distance of each measured
match's *true* correspondence from its epipolar line (:func:`self_check_truth`).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from rigsfm.core.geometry import correspondence_check
from rigsfm.core.ground import image_to_plane, undistort_pixels

UP = np.array([0.0, 0.0, 1.0])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def floor_errors(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    """``rec`` in the floor frame against the truth: camera height errors (mm) and floor normal angles (deg)."""
    by_name = {im.name: im for im in truth.images.values()}
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    heights = np.array([rec.find_image_with_name(n).projection_center()[2] - by_name[n].projection_center()[2]
                        for n in names])
    per_camera = [angle_deg(rec.find_image_with_name(n).cam_from_world().rotation.matrix() @ UP,
                            by_name[n].cam_from_world().rotation.matrix() @ UP) for n in names]
    truth_from_rec = pycolmap.estimate_sim3d(np.array([rec.find_image_with_name(n).projection_center() for n in names]),
                                             np.array([by_name[n].projection_center() for n in names]))
    return {"height_error_mm": {"max": 1000 * float(np.abs(heights).max()),
                                "median": 1000 * float(np.median(np.abs(heights)))},
            "normal_deg": {"per_camera_median": float(np.median(per_camera)), "per_camera_max": float(max(per_camera)),
                           "aligned": angle_deg(truth_from_rec.rotation.matrix() @ UP, UP)}}


def ground_distance_errors(narrow: dict, rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction,
                           height: float, seed: int = 0, samples: int = 300) -> dict:
    """Relative errors (%) of distances (> 1 m) between true points of the plane z = ``height`` seen by each
    narrow camera, mapped through the ``ground_from_image`` of narrow_poses.json."""
    rng = np.random.default_rng(seed)
    errors = []
    for entry in narrow["narrow"]:
        plane = next(g for g in entry["ground"] if g["plane_height_m"] == height)
        true_image = truth.find_image_with_name(entry["name"])
        camera = true_image.camera
        pixels = np.c_[rng.uniform(0, camera.width, samples), rng.uniform(0, camera.height, samples)]
        true_xy, ok = image_to_plane(true_image, pixels, height)
        undistorted = undistort_pixels(rec.find_image_with_name(entry["name"]).camera, pixels[ok])
        mapped = np.c_[undistorted, np.ones(len(undistorted))] @ np.asarray(plane["ground_from_image"]).T
        assert (mapped[:, 2] > 0).all()
        estimated = mapped[:, :2] / mapped[:, 2:]
        i, j = np.triu_indices(len(estimated), 1)
        d_true = np.linalg.norm(true_xy[ok][i] - true_xy[ok][j], axis=1)
        d_est = np.linalg.norm(estimated[i] - estimated[j], axis=1)
        keep = d_true > 1.0
        errors.append(100 * np.abs(d_est[keep] / d_true[keep] - 1))
    errors = np.concatenate(errors)
    return {"median": float(np.median(errors)), "p95": float(np.percentile(errors, 95)), "max": float(errors.max()),
            "pairs": int(errors.size)}


def self_check_truth(pair, estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> np.ndarray:
    """Distances (pinhole px of j) of the true correspondences of a checked pair's matched points of image i
    from their estimated epipolar lines: the true ray of each matched pixel meets the floor (z = 0: the crowd
    texture lies on it), and that point goes through ``correspondence_check``."""
    image = truth.find_image_with_name(pair.i)
    xy, ok = image_to_plane(image, pair.xy_i, 0.0)
    world = np.c_[xy[ok], np.zeros(ok.sum())]
    distances = correspondence_check(estimate, truth, pair.i, pair.j, world)
    return distances
