"""OpenCV's SIFT, with its keypoints where the features are, optionally on a reduced copy of the image.

Used where rigsfm detects features itself (floor matching, the epipolar self-check, E^sl from scene images,
ASIFT); the run's own wide-image features come from pycolmap.
"""

from __future__ import annotations

import cv2
import numpy as np

from rigsfm.core.conventions import opencv_from_resized_pixels


def opencv_sift(max_features: int = 0, contrast_threshold: float = 0.04) -> cv2.SIFT:
    """OpenCV's SIFT with ``enable_precise_upscale``: without it OpenCV doubles the image (its first octave)
    half a pixel off and every keypoint lands ~0.24 px right of and below its feature (Gaussian blobs: +0.236,
    +0.239 px; with it within 0.003 px, tests/test_sift.py), in both images of a match alike, which biases
    epipolar distances and triangulated points."""
    return cv2.SIFT_create(  # type: ignore[attr-defined]  # OpenCV's stubs lack it
        nfeatures=max_features, contrastThreshold=contrast_threshold, enable_precise_upscale=True)


def reduction_factor(shape: tuple[int, ...], size: int) -> int:
    """The integer factor that brings the longer side of an image of ``shape`` nearest ``size`` (at least 1)."""
    return max(1, round(max(shape[:2]) / size))


def detect(sift: cv2.Feature2D, gray: np.ndarray, mask: np.ndarray | None = None,
           factor: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """Keypoints (N x 2 OpenCV pixels of ``gray``) and descriptors (None when there are none) of ``gray``,
    detected on it reduced by the integer ``factor`` (cv2.INTER_AREA; the last rows and columns that do not
    fill a reduced pixel are dropped)."""
    if factor > 1:
        height, width = gray.shape[0] // factor, gray.shape[1] // factor
        gray = cv2.resize(gray[:height * factor, :width * factor], (width, height), interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask[:height * factor, :width * factor], (width, height),
                              interpolation=cv2.INTER_NEAREST)
    keypoints, descriptors = sift.detectAndCompute(gray, mask)
    xy = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    return opencv_from_resized_pixels(xy, factor), descriptors
