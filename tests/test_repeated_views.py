"""A static rig's repeated views of a point: their keypoint errors' correlation and the covariance's weights."""

from __future__ import annotations

import numpy as np
import pycolmap
import scipy.sparse as sp

from rigsfm.run.adjustment.repeated import (
    repeated_view_correlation,
    repeated_view_noise_correlation,
    repeated_view_weights,
)


def _network_with_keypoint_errors(common_px: float, own_px: float, seed: int = 0, static: bool = True) -> pycolmap.Reconstruction:
    """pycolmap's synthetic rigs, static over 3 frames each; every keypoint is the exact projection plus an error shared by
    the point's views through one camera (``common_px``) and one of its own (``own_px``), per coordinate."""
    pycolmap.set_random_seed(seed)
    rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(
        num_rigs=2, num_cameras_per_rig=2, num_frames_per_rig=3, num_points3D=300))
    for frame in rec.frames.values() if static else ():  # static rigs: every frame where the rig's first one is
        first = min(f for f in rec.frames if rec.frame(f).rig_id == frame.rig_id)
        frame.rig_from_world = rec.frame(first).rig_from_world
    rng = np.random.default_rng(seed)
    common: dict[tuple[int, int], np.ndarray] = {}
    for point_id, point in rec.points3D.items():
        for element in point.track.elements:
            image = rec.image(element.image_id)
            key = (point_id, image.camera_id)
            if key not in common:
                common[key] = rng.normal(0.0, common_px, 2)
            exact = rec.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point.xyz)
            image.points2D[element.point2D_idx].xy = np.asarray(exact) + common[key] + rng.normal(0.0, own_px, 2)
    if common_px + own_px > 0:  # residuals of a fit, as the adjustment leaves them
        options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False, refine_principal_point=False,
                                                   refine_extra_params=False, print_summary=False)
        pycolmap.bundle_adjustment(rec, options)
    return rec


def test_correlation_of_repeated_views():
    """0.2 px shared and 0.1 px own: noise correlation 0.8 on every camera; independent errors: 0; exact keypoints
    and rigs that move between frames: no repeated views. The weighting error (3x the noise) adds a part that
    repeats: 1 - (1 - 0.8) / 9."""
    correlated = _network_with_keypoint_errors(0.2, 0.1)
    noise = repeated_view_noise_correlation(correlated)
    assert len(noise) == 4 and all(abs(rho - 0.8) < 0.1 for rho in noise.values())
    assert all(abs(rho - (1 - (1 - noise[c]) / 9)) < 1e-12 for c, rho in repeated_view_correlation(correlated, 3.0).items())
    assert all(rho < 0.05 for rho in repeated_view_noise_correlation(_network_with_keypoint_errors(0.0, 0.2)).values())
    assert repeated_view_noise_correlation(_network_with_keypoint_errors(0.0, 0.0)) == {}
    assert repeated_view_noise_correlation(_network_with_keypoint_errors(0.2, 0.1, static=False)) == {}


def test_weights_of_repeated_views():
    """Rows of three observations of point 0 through camera 7, one of point 0 through camera 8, one of point 1
    through camera 7, and a prior row: n = 3 gets 1 / sqrt(1 + 2 rho), the others 1."""
    num_a = 4  # columns 0-1: camera 7, 2-3: camera 8; then 3 per point
    rows = []
    for camera_columns, point in (((0, 1), 0), ((0, 1), 0), ((0, 1), 0), ((2, 3), 0), ((0, 1), 1)):
        for _ in range(2):
            row = np.zeros(num_a + 6)
            row[list(camera_columns)] = 1.0
            row[num_a + 3 * point: num_a + 3 * point + 3] = 1.0
            rows.append(row)
    rows.append(np.r_[1.0, np.zeros(num_a + 5)])
    jac = sp.csr_matrix(np.array(rows))
    camera_of_column = np.array([7, 7, 8, 8])
    weights = repeated_view_weights(jac, num_a, camera_of_column, {7: 0.75, 8: 0.75})
    np.testing.assert_allclose(weights[:6], 1.0 / np.sqrt(2.5))
    np.testing.assert_allclose(weights[6:], 1.0)
    np.testing.assert_allclose(repeated_view_weights(jac, num_a, camera_of_column, {8: 0.75}), 1.0)


def test_a_repeated_static_frame_adds_no_information(tmp_path):
    """A second frame of a static rig whose wide keypoints repeat the first's exactly tells nothing new: the other
    rigs' pose uncertainty stays that of the one-frame network (within 5 %; counted as independent views, the
    repeated keypoints made it smaller by more than that)."""
    from pathlib import Path

    from synthetic_db import make_network, perturbed_model
    from test_static_frames import _second_static_frame

    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.adjustment.covariance import joint_covariance
    from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec

    net = make_network(tmp_path, num_rigs=3, seed=3)
    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    metres = float(np.linalg.norm(net.ground_truth.find_image_with_name(a).projection_center()
                                  - net.ground_truth.find_image_with_name(b).projection_center()))
    spec = ScaleSpec(Path(tmp_path / "scale.yaml"), (CameraDistance(a, b, metres),), ())
    sigmas = []
    for repeated in (False, True):
        mapped = perturbed_model(net.ground_truth, seed=3)
        if repeated:
            _second_static_frame(mapped, "rig01", np.zeros(3))
        result = adjust(mapped, net.rigs, spec)
        frame_id = result.reconstruction.find_image_with_name("rig02/wide/frame0000.png").frame_id
        sigmas.append(joint_covariance(result).sigma(("frame", frame_id))[:3])
    np.testing.assert_allclose(sigmas[1], sigmas[0], rtol=0.05)
