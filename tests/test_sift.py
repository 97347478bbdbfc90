"""OpenCV SIFT as rigsfm uses it (rigsfm.core.sift): keypoints where the features are, also on reduced images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigsfm.core.sift import detect, opencv_sift, reduction_factor


def blobs(seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A 400x600 image of Gaussian blobs (sigma 6 px) at known sub-pixel OpenCV pixels."""
    rng = np.random.default_rng(seed)
    centres = np.array([[x, y] for x in range(60, 560, 90) for y in range(60, 360, 90)], float)
    centres += rng.uniform(-0.5, 0.5, centres.shape)
    ys, xs = np.mgrid[0:400, 0:600]
    image = sum(np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * 6.0**2)) for cx, cy in centres)
    return (40 + 180 * image).astype(np.uint8), centres


def offsets(xy: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Each blob's nearest keypoint minus the blob's centre."""
    nearest = np.linalg.norm(xy[None] - centres[:, None], axis=2).argmin(axis=1)
    return xy[nearest] - centres


@pytest.mark.parametrize("factor", [1, 2, 3])
def test_keypoints_sit_on_the_blobs(factor):
    gray, centres = blobs()
    xy, descriptors = detect(opencv_sift(), gray, factor=factor)
    assert descriptors is not None and len(descriptors) == len(xy)
    error = np.linalg.norm(offsets(xy, centres), axis=1)
    assert np.median(error) < 0.05 and error.max() < 0.1  # plain cv2.SIFT_create: 0.34 px


def test_plain_opencv_sift_is_a_quarter_pixel_off():
    """Why opencv_sift exists: OpenCV's default upsampling moves every keypoint right and down."""
    gray, centres = blobs()
    keypoints = cv2.SIFT_create().detect(gray, None)
    shift = np.median(offsets(np.array([k.pt for k in keypoints]), centres), axis=0)
    np.testing.assert_allclose(shift, [0.24, 0.24], atol=0.03)


def test_mask_is_reduced_with_the_image():
    gray, centres = blobs()
    mask = np.zeros(gray.shape, np.uint8)
    mask[:, :300] = 255
    xy, _ = detect(opencv_sift(), gray, mask, factor=2)
    assert len(xy) and (xy[:, 0] < 300).all()
    assert np.linalg.norm(offsets(xy, centres[centres[:, 0] < 280]), axis=1).max() < 0.1


def test_reduction_factor():
    assert reduction_factor((1234, 1624), 800) == 2
    assert reduction_factor((617, 812), 800) == 1
    assert reduction_factor((100, 100), 800) == 1
    assert reduction_factor((3000, 4000, 3), 800) == 5
