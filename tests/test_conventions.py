import cv2
import numpy as np
import pycolmap
import pytest

from rigsfm.core.conventions import (
    colmap_from_opencv_pixels,
    euler_zyx_degrees,
    opencv_from_colmap_pixels,
    opencv_from_resized_pixels,
    opengl_c2w_from_cam_from_world,
    rotation_angle_deg,
    rotation_from_euler_zyx_degrees,
    rotation_from_wxyz,
    rotation_vector,
    wxyz_from_rotation,
)


def test_quaternion_wxyz_round_trip_and_order():
    # 90 degrees about z: w = cos(45), z = sin(45)
    rotation = rotation_from_wxyz([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(rotation.matrix(), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(rotation.quat, [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=1e-12)
    np.testing.assert_allclose(wxyz_from_rotation(rotation), [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])


def test_wxyz_has_non_negative_w():
    q = wxyz_from_rotation(pycolmap.Rotation3d(np.array([0.0, 0.0, -0.6, -0.8])))
    assert q[0] == pytest.approx(0.8) and q[3] == pytest.approx(0.6)


def test_pixel_centre_conversion():
    xy = np.array([[0.0, 0.0], [10.0, 20.0]])
    np.testing.assert_allclose(colmap_from_opencv_pixels(xy), [[0.5, 0.5], [10.5, 20.5]])
    np.testing.assert_allclose(opencv_from_colmap_pixels(colmap_from_opencv_pixels(xy)), xy)


@pytest.mark.parametrize(("factor", "interpolation"), [(2, cv2.INTER_AREA), (3, cv2.INTER_AREA),
                                                       (2.5, cv2.INTER_LINEAR), (0.5, cv2.INTER_LINEAR)])
def test_resized_pixel_centres(factor, interpolation):
    """A ramp whose value is each pixel's own x: resized, each pixel holds the original x of its centre."""
    ramp = np.tile(np.arange(60, dtype=np.float32), (30, 1))
    resized = cv2.resize(ramp, None, fx=1 / factor, fy=1 / factor, interpolation=interpolation)
    x = np.arange(resized.shape[1], dtype=np.float64)
    inner = slice(2, -2)  # away from the borders, which are clamped
    np.testing.assert_allclose(resized[5, inner], opencv_from_resized_pixels(np.c_[x, x], factor)[inner, 0], atol=1e-4)


def test_pixel_convention_matches_colmap_projection():
    """COLMAP projects the optical axis to (cx, cy); a pixel's centre is at integer + 0.5."""
    camera = pycolmap.Camera(model="PINHOLE", width=4, height=2, params=[1.0, 1.0, 2.0, 1.0])
    np.testing.assert_allclose(camera.img_from_cam(np.array([[0.0, 0.0, 1.0]])), [[2.0, 1.0]])
    # The centre of the first pixel in OpenCV's convention (0, 0) is COLMAP's (0.5, 0.5).
    ray = camera.cam_from_img(colmap_from_opencv_pixels(np.array([[0.0, 0.0]])))
    np.testing.assert_allclose(ray, [[-1.5, -0.5]])


@pytest.mark.parametrize("angles", [(10.0, -20.0, 30.0), (-170.0, 45.0, 5.0), (0.0, 0.0, 0.0), (90.0, 89.0, -90.0)])
def test_euler_round_trip(angles):
    r = rotation_from_euler_zyx_degrees(*angles)
    np.testing.assert_allclose(euler_zyx_degrees(r), angles, atol=1e-9)


def test_euler_convention_is_z_then_y_then_x():
    r = rotation_from_euler_zyx_degrees(30.0, 0.0, 0.0)
    np.testing.assert_allclose(r @ [1, 0, 0], [np.cos(np.radians(30)), np.sin(np.radians(30)), 0], atol=1e-12)


def test_opengl_axes():
    cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.0, 0.0, 5.0]))
    c2w = opengl_c2w_from_cam_from_world(cam_from_world)
    np.testing.assert_allclose(c2w[:3, 3], [0, 0, -5])
    # OpenGL looks down -z: the camera's forward (+z in OpenCV) is -z_gl.
    np.testing.assert_allclose(c2w[:3, :3] @ [0, 0, -1], [0, 0, 1])
    np.testing.assert_allclose(c2w[:3, :3] @ [0, 1, 0], [0, -1, 0])


def test_rotation_angle():
    a = rotation_from_euler_zyx_degrees(0.0, 0.0, 0.0)
    b = rotation_from_euler_zyx_degrees(0.0, 0.0, 0.25)
    assert rotation_angle_deg(a, b) == pytest.approx(0.25, abs=1e-9)


def test_rotation_vector_inverts_axis_angle():
    for vector in ([0.3, -0.2, 0.1], [0.0, 0.0, 1e-9], [0.0, 3.0, 0.0], [-1.2, 0.4, 2.0]):
        rotation = pycolmap.Rotation3d(axis_angle=np.array(vector))
        np.testing.assert_allclose(rotation_vector(rotation), vector, atol=1e-12)
    # not the [w, x, y, z] reading of the same numbers: 90 deg about z is (0, 0, pi/2)
    quarter = pycolmap.Rotation3d(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(rotation_vector(quarter), [0.0, 0.0, np.pi / 2], atol=1e-12)
