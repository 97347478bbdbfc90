"""Affine-robust features (ASIFT) for wide views with a large perspective change between rigs.

OpenCV's ``AffineFeature`` runs SIFT on affinely warped copies of the image (simulated tilts and
rotations) and maps the keypoints back. The result is stored in the database exactly like COLMAP's own
SIFT, so COLMAP's matcher and verification handle it unchanged:

- keypoints in COLMAP's pixel convention (OpenCV + 0.5) as COLMAP's 6-column affine shape
  (x, y, a11, a12, a21, a22) built from OpenCV's size (scale = size / 2) and angle;
- descriptors as COLMAP's extractor writes them: RootSIFT (L1-normalise, square root; unit L2 norm),
  then ``min(255, round(512 * v))`` as uint8, type SIFT. COLMAP's matcher takes the dot product of two
  such rows divided by 512^2 as the cosine of the descriptor angle.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.conventions import colmap_from_opencv_pixels
from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image
from rigsfm.core.sift import opencv_sift
from rigsfm.run.inputs.database import open_database

logger = logging.getLogger(__name__)


def colmap_sift_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Float SIFT descriptors (N x 128) -> COLMAP's uint8 L1-root form (as its extractor stores them)."""
    d = np.asarray(descriptors, dtype=np.float64).reshape(-1, 128)
    d = np.sqrt(d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12))
    return np.minimum(255, np.round(512.0 * d)).astype(np.uint8)


def colmap_keypoints(keypoints: Sequence[cv2.KeyPoint]) -> np.ndarray:
    """OpenCV keypoints -> COLMAP's (x, y, a11, a12, a21, a22) rows in COLMAP pixels (float32)."""
    if not keypoints:
        return np.zeros((0, 6), np.float32)
    xy = colmap_from_opencv_pixels(np.array([k.pt for k in keypoints]))
    scale = np.array([k.size for k in keypoints]) / 2.0
    angle = np.radians([k.angle for k in keypoints])
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    return np.column_stack([xy, c, -s, s, c]).astype(np.float32)


def asift_features(gray: np.ndarray, max_num_features: int) -> tuple[np.ndarray, np.ndarray]:
    """ASIFT keypoints and descriptors of one grey image, the strongest ``max_num_features`` kept."""
    detector = cv2.AffineFeature_create(opencv_sift())  # type: ignore[attr-defined]  # OpenCV's stubs lack it
    keypoints, descriptors = detector.detectAndCompute(gray, None)
    if descriptors is None or not keypoints:
        return np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8)
    order = np.argsort([-k.response for k in keypoints], kind="stable")
    # The simulated views detect the same corner several times with near-identical descriptors, which
    # makes every such match fail the ratio test: keep the strongest keypoint per 2-px cell.
    cells = np.array([(int(keypoints[i].pt[0] // 2), int(keypoints[i].pt[1] // 2)) for i in order])
    _, first = np.unique(cells, axis=0, return_index=True)
    order = order[np.sort(first)][:max_num_features]
    return colmap_keypoints([keypoints[i] for i in order]), colmap_sift_descriptors(descriptors[order])


def extract_asift(
    database_path: Path,
    image_dir: Path,
    names: Sequence[str],
    max_num_features: int,
    progress: Callable[[int, int], None] | None = None,
) -> int:
    """ASIFT for each named image (``<rig>/<sensor>/<file>`` under ``image_dir``) into the database."""
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        for done, name in enumerate(names, start=1):
            gray = read_image(Path(image_dir) / name, cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise InputError(f"{Path(image_dir) / name}: cannot be read as an image; replace it")
            keypoints, descriptors = asift_features(gray, max_num_features)
            with pycolmap.DatabaseTransaction(database):
                database.write_keypoints(ids[name], keypoints)
                database.write_descriptors(
                    ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, descriptors)
                )
            logger.info("ASIFT %s: %d keypoints", name, len(keypoints))
            if progress:
                progress(done, len(names))
    return len(names)
