"""Stage 4, matching: matching and geometric verification of the selected pairs (COLMAP's matcher, or a direct SIFT matcher
for pairs files)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.run.inputs.database import open_database
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.matching.extract import Progress
from rigsfm.run.matching.gpu import pycolmap_device, use_gpu
from rigsfm.run.matching.pairs import PairSelection, select_pairs
from rigsfm.run.options import MatchingOptions

logger = logging.getLogger(__name__)


def match_features(
    database_path: Path,
    images: Sequence[ImageEntry],
    options: MatchingOptions,
    pairs_path: Path,
    progress: Progress | None = None,
    batch_size: int = 150,
    *,
    num_threads: int = -1,
    selection: PairSelection | None = None,
) -> int:
    """Match and verify every selected pair not verified yet; returns how many pairs were matched now.

    Pairs go to COLMAP in batches of ``batch_size`` (each call loads its images' descriptors and builds
    their indexes once, so small batches cost more CPU time)."""
    selection = selection or select_pairs(database_path, images, options)
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        todo = [(a, b) for a, b in selection.pairs if not database.exists_two_view_geometry(ids[a], ids[b])]
    if progress and not todo:  # every pair verified before: the stage is done, not still counting
        progress(len(selection.pairs), len(selection.pairs))
    gpu = use_gpu(options.device)
    matching = pycolmap.FeatureMatchingOptions(
        num_threads=num_threads, use_gpu=gpu, rig_verification=options.resolved_rig_verification
    )
    matching.sift.max_ratio = options.max_ratio
    matching.sift.cross_check = options.cross_check
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = options.max_error_px
    # Calibrated cameras: keep the essential-matrix model unless a homography explains nearly every
    # inlier (COLMAP's 0.8 labels far walls seen by distant rigs "planar" and the mappers then fail).
    verification.max_H_inlier_ratio = options.max_homography_inlier_ratio
    verification.ransac.random_seed = 0
    direct = [pair for pair in todo if not all(fits_pairs_file(name) for name in pair)]
    todo = [pair for pair in todo if all(fits_pairs_file(name) for name in pair)] + direct
    plain = todo[: len(todo) - len(direct)]

    def match_listed(pairs: Sequence[tuple[str, str]]) -> None:
        """COLMAP's matcher on ``pairs`` through the pairs file (none: only its rig verification runs)."""
        pairs_path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        pycolmap.match_image_pairs(
            database_path,
            matching_options=matching,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
            verification_options=verification,
            device=pycolmap_device(gpu),
        )

    for start in range(0, len(plain), batch_size):
        batch = plain[start : start + batch_size]
        match_listed(batch)
        if progress:
            progress(start + len(batch), len(todo))
    if direct:
        match_pairs_directly(database_path, direct, matching, verification,
                             (lambda done, _: progress(len(plain) + done, len(todo))) if progress else None)
        if matching.rig_verification:  # an empty pairs file: COLMAP's matcher then only runs its rig verification
            match_listed([])
    pairs_path.unlink(missing_ok=True)
    logger.info("Matched %d image pairs", len(todo))
    return len(todo)


def fits_pairs_file(name: str) -> bool:
    """Whether COLMAP's imported-pairs reader reads ``name`` back: it splits each line at the first space and
    skips lines that start with '#' (``ReadImagePairsText`` in colmap/controllers/pairing.cc), so names with
    whitespace (``rig 01/wide/frame 0000.png``) or a leading '#' have no place in the pairs file."""
    return not name.startswith("#") and not any(c.isspace() for c in name)


SIFT_NORM_SQUARED = 512.0**2  # COLMAP's uint8 SIFT descriptors have L2 norm 512 (kSqSiftDescriptorNorm)


def _best_two(squared: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along ``axis``: the index of the nearest and the squared distances of the nearest two (inf if there is
    one). Two passes of min (argpartition is much slower here); ``squared`` is restored afterwards."""
    best = np.expand_dims(np.argmin(squared, axis=axis), axis)
    first = np.take_along_axis(squared, best, axis)
    if squared.shape[axis] < 2:
        second = np.full_like(first, np.inf)
    else:
        np.put_along_axis(squared, best, np.inf, axis)
        second = np.min(squared, axis=axis, keepdims=True)
        np.put_along_axis(squared, best, first, axis)
    return best.squeeze(axis), first.squeeze(axis), second.squeeze(axis)


def _accept(first: np.ndarray, second: np.ndarray, max_ratio: float, max_distance: float) -> np.ndarray:
    """COLMAP's FindBestMatchesOneWayIndex tests: the distance threshold and the ratio test."""
    return (first <= SIFT_NORM_SQUARED * max_distance**2) & (np.sqrt(first) < max_ratio * np.sqrt(second))


def match_sift(descriptors1: np.ndarray, descriptors2: np.ndarray, max_ratio: float, max_distance: float,
               cross_check: bool, block: int = 1024) -> np.ndarray:
    """COLMAP's SIFT matching of two images' uint8 descriptors (ratio test, distance threshold, cross check) with
    exact nearest neighbours; returns an (N, 2) uint32 array of keypoint indices."""
    if len(descriptors1) == 0 or len(descriptors2) == 0:
        return np.zeros((0, 2), np.uint32)
    d1, d2 = np.asarray(descriptors1, np.float32), np.asarray(descriptors2, np.float32)
    norms2 = (d2 * d2).sum(1)
    one_two = np.full(len(d1), -1, np.int64)
    column_index, column_distance = [], []  # per block of rows: each column's nearest row and nearest two distances
    for start in range(0, len(d1), block):
        rows = d1[start : start + block]
        squared = np.maximum((rows * rows).sum(1)[:, None] + norms2[None, :] - 2.0 * (rows @ d2.T), 0.0)
        best, first, second = _best_two(squared, axis=1)
        one_two[start : start + len(rows)] = np.where(_accept(first, second, max_ratio, max_distance), best, -1)
        if cross_check:
            best, first, second = _best_two(squared, axis=0)
            column_index += [best + start, np.full_like(best, -1)]
            column_distance += [first, second]
    matched = np.flatnonzero(one_two >= 0)
    if cross_check:
        pick, first, second = _best_two(np.stack(column_distance), axis=0)
        best = np.stack(column_index)[pick, np.arange(len(d2))]
        two_one = np.where(_accept(first, second, max_ratio, max_distance), best, -1)
        matched = matched[two_one[one_two[matched]] == matched]
    return np.stack([matched, one_two[matched]], axis=1).astype(np.uint32)


def match_pairs_directly(database_path: Path, pairs: Sequence[tuple[str, str]],
                         matching: pycolmap.FeatureMatchingOptions, verification: pycolmap.TwoViewGeometryOptions,
                         progress: Progress | None = None) -> None:
    """Match and verify ``pairs`` one at a time, for the names the pairs file cannot carry (:func:`fits_pairs_file`).

    Matching is COLMAP's SIFT matching (:func:`match_sift`; pycolmap's ``FeatureMatcher.match`` would do the same
    but, without COLMAP's descriptor index, takes ~30 s per pair of 5000 features), verification pycolmap's
    ``estimate_two_view_geometry`` with the options of the pairs-file path, written as COLMAP's matcher writes them
    (fewer than ``min_num_inliers`` matches or inliers are stored as none). Raw matches already stored (an
    interrupted run) are verified, not matched again."""
    minimum = verification.min_num_inliers
    with open_database(database_path) as database:
        images = {image.name: image for image in database.read_all_images()}
        for done, (a, b) in enumerate(pairs, start=1):
            id1, id2 = images[a].image_id, images[b].image_id
            if database.exists_matches(id1, id2):
                matches = database.read_matches(id1, id2)
            else:
                matches = match_sift(database.read_descriptors(id1).data, database.read_descriptors(id2).data,
                                     matching.sift.max_ratio, matching.sift.max_distance, matching.sift.cross_check)
                if len(matches) < minimum:
                    matches = np.zeros((0, 2), np.uint32)
                database.write_matches(id1, id2, matches)
            geometry = pycolmap.TwoViewGeometry()
            if len(matches) >= minimum:
                geometry = pycolmap.estimate_two_view_geometry(
                    database.read_camera(images[a].camera_id), database.read_keypoints(id1)[:, :2].astype(np.float64),
                    database.read_camera(images[b].camera_id), database.read_keypoints(id2)[:, :2].astype(np.float64),
                    matches, verification)
                if len(geometry.inlier_matches) < minimum:
                    geometry = pycolmap.TwoViewGeometry()
            if database.exists_two_view_geometry(id1, id2):
                database.delete_two_view_geometry(id1, id2)
            database.write_two_view_geometry(id1, id2, geometry)
            if progress:
                progress(done, len(pairs))
