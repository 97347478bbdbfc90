"""Observations weighed at their own noise (heads: rigsfm.run.narrow.heads, step 6; JointProblem's point_sigmas)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.adjustment.model import estimate_pixel_sigma
from rigsfm.run.adjustment.priors import calibration_priors
from rigsfm.run.adjustment.problem import JointProblem
from rigsfm.run.adjustment.result import Gauge
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec
from rigsfm.run.options import AdjustOptions

HEAD_NOISE_PX = 2.0  # per coordinate, four times the keypoints' 0.5 px


@pytest.fixture(scope="module")
def network_with_heads(tmp_path_factory):
    """A 4-rig network of keypoints (0.5 px) with narrow observations, where 60 points seen by three or more narrow
    cameras (the 'heads') err ``HEAD_NOISE_PX`` in every image. Returns the network, the model, the heads' point
    ids and a scale spec."""
    from synthetic_db import make_network, perturbed_model

    root = tmp_path_factory.mktemp("heads")
    net = make_network(root, num_rigs=4, seed=5, narrow_observations=True)
    truth = net.ground_truth
    model = perturbed_model(truth, seed=5, narrow_observations=True)
    narrow = {im.image_id for im in model.images.values() if "/narrow/" in im.name}
    head_ids = [point_id for point_id, point in sorted(model.points3D.items())
                if sum(e.image_id in narrow for e in point.track.elements) >= 3][:60]
    assert len(head_ids) >= 30
    rng = np.random.default_rng(5)
    extra = np.sqrt(HEAD_NOISE_PX**2 - 0.5**2)  # on top of perturbed_model's 0.5 px
    for point_id in head_ids:
        for element in model.points3D[point_id].track.elements:
            point2D = model.image(element.image_id).points2D[element.point2D_idx]
            point2D.xy = np.asarray(point2D.xy) + rng.normal(0.0, extra, 2)
    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    metres = float(np.linalg.norm(truth.find_image_with_name(a).projection_center()
                                  - truth.find_image_with_name(b).projection_center()))
    spec = ScaleSpec(Path(root / "scale.yaml"), (CameraDistance(a, b, metres),), ())
    return net, model, head_ids, spec


def _squared_reprojection(model, point_ids) -> float:
    total = 0.0
    for point_id in point_ids:
        point = model.points3D[point_id]
        for element in point.track.elements:
            image = model.image(element.image_id)
            camera = model.cameras[image.camera_id]
            projected = np.asarray(camera.img_from_cam(image.cam_from_world() * point.xyz[None]))[0]
            total += float(np.sum((projected - np.asarray(image.points2D[element.point2D_idx].xy)) ** 2))
    return total


def test_a_points_own_noise_weighs_its_residuals(network_with_heads):
    """Each residual of a point of ``point_sigmas`` is its reprojection error times ``weight_sigma / sigma``; every
    other residual is unchanged (the squared loss: the covariance's problem)."""
    net, model, head_ids, _ = network_with_heads
    priors = calibration_priors(net.rigs)
    sigma = 0.5
    costs = []
    for point_sigmas in (None, dict.fromkeys(head_ids, 4.0 * sigma * AdjustOptions().pixel_sigma_inflation)):
        # (no scale spec: pyceres' evaluate_residuals does not hold the GIL that its Python cost functions need)
        problem = JointProblem(model, net.rigs, priors, None, AdjustOptions(), sigma, gauge=Gauge.RIGID,
                               robust=False, point_sigmas=point_sigmas)
        residuals = np.asarray(problem.problem.evaluate_residuals())
        costs.append((float(np.sum(residuals**2)), len(residuals)))
    heads = _squared_reprojection(model, head_ids)
    assert heads > 0.03 * costs[0][0]  # the heads' share is far larger than the tolerance below
    assert costs[1][1] == costs[0][1]
    assert costs[1][0] == pytest.approx(costs[0][0] - heads + heads / 16.0, rel=1e-6)


def test_points_at_their_own_noise_leave_the_pooled_noise_to_the_keypoints(network_with_heads):
    """The pooled pixel noise is the keypoints' (0.5 px) with the heads weighed at their own; pooled with them it
    was inflated, and every prior and measurement weighed against it. Without point_sigmas the adjustment is
    bit-identical to one that never had the option (floor matches, --narrow off)."""
    net, model, head_ids, spec = network_with_heads
    pooled = adjust(model, net.rigs, spec, with_covariance=False)
    own = adjust(model, net.rigs, spec, with_covariance=False, point_sigmas=dict.fromkeys(head_ids, HEAD_NOISE_PX))
    assert own.pixel_sigma == pytest.approx(0.5, rel=0.15), own.pixel_sigma
    assert pooled.pixel_sigma > 1.3 * own.pixel_sigma, (pooled.pixel_sigma, own.pixel_sigma)
    # the last round's estimate, before the final solve
    assert own.pixel_sigma == pytest.approx(estimate_pixel_sigma(own.reconstruction, 4.0, head_ids), rel=0.01)
    empty = adjust(model, net.rigs, spec, with_covariance=False, point_sigmas={})
    for image_id, image in pooled.reconstruction.images.items():
        assert np.array_equal(image.cam_from_world().matrix(),
                              empty.reconstruction.image(image_id).cam_from_world().matrix())


def _sensor_rotations(model, camera_ids) -> list[np.ndarray]:
    out = []
    for camera_id in camera_ids:
        image = next(im for im in model.images.values() if im.camera_id == camera_id)
        rig = model.rigs[model.frames[image.frame_id].rig_id]
        out.append(rig.sensor_from_rig(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id)).rotation.matrix())
    return out


def test_a_views_shared_head_error_widens_the_covariance_by_the_estimates_response(network_with_heads):
    """With ``point_shared_sigma`` (one offset per view and image coordinate shared by its heads,
    rigsfm.run.adjustment.heads_error) the narrow E^sl's covariance grows by the spread of the adjustment's own
    response to those offsets: every view's heads shifted by 1 px, one coordinate at a time, and the problem solved
    again (squared loss, as the covariance). Without it the covariance is the heads-as-independent one."""
    from rigsfm.run.adjustment.covariance import joint_covariance

    net, model, head_ids, spec = network_with_heads
    sigmas = dict.fromkeys(head_ids, HEAD_NOISE_PX)
    result = adjust(model, net.rigs, spec, point_sigmas=sigmas)
    result.covariance = None
    independent = joint_covariance(result)
    shared_px = 5.0  # the synthetic narrow cameras' keypoints hold E^sl far better than a crowd's heads do
    result.point_shared_sigma = shared_px
    shared = joint_covariance(result)
    assert independent is not None and shared is not None

    def solved(start: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
        problem = JointProblem(start, result.rigs, result.priors, result.scale_spec, result.options,
                               result.pixel_sigma, gauge=Gauge.RIGID, robust=False, held_rigs=result.held_rigs,
                               point_sigmas=sigmas)
        problem.solve_to_convergence()
        return start

    base = solved(pycolmap.Reconstruction(result.reconstruction))
    narrow = sorted({im.camera_id for im in base.images.values() if "/narrow/" in im.name})
    before = _sensor_rotations(base, narrow)
    viewers = sorted({e.image_id for point_id in head_ids for e in base.points3D[point_id].track.elements})
    responses = []
    for image_id in viewers:
        for coordinate in range(2):
            shifted = pycolmap.Reconstruction(base)
            for point_id in head_ids:
                for element in shifted.points3D[point_id].track.elements:
                    if element.image_id == image_id:
                        point2D = shifted.image(image_id).points2D[element.point2D_idx]
                        xy = np.asarray(point2D.xy).copy()
                        xy[coordinate] += 1.0
                        point2D.xy = xy
            response = []
            for r0, r1 in zip(before, _sensor_rotations(solved(shifted), narrow)):
                d = r1 @ r0.T  # R' = Exp(w) R
                response += [(d[2, 1] - d[1, 2]) / 2, (d[0, 2] - d[2, 0]) / 2, (d[1, 0] - d[0, 1]) / 2]
            responses.append(np.array(response))
    spread = shared_px**2 * sum(np.outer(r, r) for r in responses)
    index = np.concatenate([independent.index([("sensor_from_rig", c)])[:3] for c in narrow])  # rotations
    added = shared.covariance[np.ix_(index, index)] - independent.covariance[np.ix_(index, index)]
    assert np.all(np.diag(spread) > 0.01 * np.diag(independent.covariance[np.ix_(index, index)]))
    assert np.linalg.norm(added - spread) < 0.03 * np.linalg.norm(spread), (np.diag(added), np.diag(spread))
