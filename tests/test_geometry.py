"""The one projection helper, the one Sampson error and the one serialiser, against closed forms."""

import numpy as np
import pycolmap
import pytest

from rigsfm.core.geometry import align_points, project, project_world, sampson, sampson_error_px
from rigsfm.core.serialise import camera_from_dict, camera_to_dict, pose_from_dict, pose_to_dict

# The arena's wide lens: strong barrel distortion, so the polynomial turns back beyond the field of view.
WIDE = pycolmap.Camera(model="OPENCV", width=1624, height=1234, params=[900.0, 900.0, 812.0, 617.0, -0.1, 0.0, 0.0,
                                                                          0.0])


def test_points_the_distortion_folds_back_are_not_seen():
    # radius 3 (71.6 deg off axis): 3 (1 - 0.1 * 9) = 0.3, i.e. 270 px from the centre, well inside the image.
    folded = np.array([[3.0, 0.0, 1.0]])
    xy_raw = np.asarray(WIDE.img_from_cam(folded))
    assert 0 < xy_raw[0, 0] < WIDE.width  # the trap: pycolmap puts it inside the image
    xy, seen = project(WIDE, folded)
    assert not seen[0] and np.isnan(xy[0]).all()
    inside = np.array([[0.3, 0.2, 1.0], [0.0, 0.0, 5.0]])
    xy, seen = project(WIDE, inside)
    assert seen.all()
    np.testing.assert_allclose(xy, np.asarray(WIDE.img_from_cam(inside)))


def test_behind_outside_and_margin():
    # x = 1.5 is before the fold (the polynomial turns back at 1 / sqrt(0.3) = 1.83) but beyond the border
    points = np.array([[0.0, 0.0, -1.0], [1.5, 0.0, 1.0], [0.9, 0.0, 1.0]])
    xy, seen = project(WIDE, points)
    assert seen.tolist() == [False, False, True]  # behind; beyond the image border; inside (x ~ 1556 px)
    _, seen = project(WIDE, points, margin_px=100.0)
    assert not seen[2]
    _, seen = project(WIDE, points, margin_px=None)
    assert seen.tolist() == [False, True, True]  # the image border does not matter, the fold does


def test_project_world_matches_the_camera_frame():
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(axis_angle=np.array([0.1, -0.2, 0.05])), np.array([0.3, -1.0, 4.0]))
    world = np.array([[0.2, 0.1, 1.0], [-0.5, 0.3, 2.0]])
    np.testing.assert_allclose(project_world(WIDE, pose, world)[0], project(WIDE, np.asarray(pose * world))[0])


def test_sampson_is_the_distance_to_the_line_for_a_pure_translation():
    # Cameras side by side (t along x): epipolar lines are horizontal; the Sampson distance of (x, y) and
    # (x', y') is the least total displacement of both points onto one line: |y - y'| / sqrt(2).
    essential = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # [t]x, t = (1, 0, 0)
    x1 = np.array([[0.1, 0.2], [0.3, -0.1]])
    x2 = np.array([[0.0, 0.26], [0.2, -0.1]])
    np.testing.assert_allclose(np.abs(sampson(essential, x1, x2)), [0.06 / np.sqrt(2), 0.0], atol=1e-12)
    camera = pycolmap.Camera(model="PINHOLE", width=1000, height=1000, params=[1000.0, 1000.0, 500.0, 500.0])
    pixels1, pixels2 = x1 * 1000 + 500, x2 * 1000 + 500
    np.testing.assert_allclose(sampson_error_px(essential, camera, camera, pixels1, pixels2), [60 / np.sqrt(2), 0.0], atol=1e-9)


def test_serialiser_round_trips_exactly():
    assert camera_to_dict(camera_from_dict(camera_to_dict(WIDE))) == camera_to_dict(WIDE)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(axis_angle=np.array([0.3, 0.1, -0.2])), np.array([1.0, 2.0, 3.0]))
    data = pose_to_dict(pose)
    assert data["quaternion_wxyz"][0] >= 0 and "quaternion_wxyz" not in pose_to_dict(pose, quaternion=False)
    np.testing.assert_allclose(pose_from_dict(data).matrix(), pose.matrix(), atol=1e-15)
    w, x, y, z = data["quaternion_wxyz"]
    np.testing.assert_allclose(pycolmap.Rotation3d(np.array([x, y, z, w])).matrix(), pose.rotation.matrix(), atol=1e-15)


@pytest.mark.parametrize("camera", [WIDE, pycolmap.Camera(model="OPENCV", width=1624, height=1234,
                                                          params=[3600.0, 3600.0, 812.0, 617.0, 0.04, -0.1, 0, 0])])
def test_every_seen_pixel_maps_back_onto_its_ray(camera):
    rng = np.random.default_rng(0)
    rays = np.column_stack([rng.uniform(-4, 4, (4000, 2)), np.ones(4000)])
    xy, seen = project(camera, rays)
    back = np.asarray(camera.cam_from_img(xy[seen]))
    np.testing.assert_allclose(back, rays[seen, :2], atol=1e-5)
    assert 0 < seen.sum() < len(rays)


def test_align_points_recovers_a_similarity_and_refuses_a_line():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(6, 3))
    quaternion = np.array([0.1, -0.3, 0.2, 0.9])  # xyzw
    truth = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(quaternion / np.linalg.norm(quaternion)), np.array([1.0, -2.0, 0.5]))
    target = truth * source
    found = align_points(source, target, scaled=True)
    np.testing.assert_allclose(found.matrix(), truth.matrix(), atol=1e-9)
    rigid = align_points(source, target, scaled=False)  # no scale: it stays in the residual
    assert rigid.scale == 1.0
    np.testing.assert_allclose(rigid.rotation.matrix(), truth.rotation.matrix(), atol=1e-9)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    assert align_points(line, line + 1.0, scaled=False) is None and align_points(source[:2], target[:2],
                                                                                   scaled=True) is None
