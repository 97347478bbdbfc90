"""Stage 2: SIFT features and matching with geometric verification.

Wide images always get features. Narrow images stay featureless unless ``narrow_features`` (their view
is homogeneous by design; features there only cost time and add outliers). Work already in the database
(keypoints of an image, a verified pair) is kept, so an interrupted run resumes where it stopped; work
made with other settings is cleared first (``drop_stale_work``).
"""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.run.inputs import ImageEntry
from rigsfm.run.options import Features, MatchingOptions
from rigsfm.core.io import write_json_atomic
from rigsfm.run.database import open_database

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


def _settings(options: MatchingOptions) -> dict:
    """What the stored features and matches depend on (threads do not count)."""
    return {
        "features": {"type": str(options.features), "max_num_features": options.max_num_features,
                     "narrow_features": options.narrow_features},
        "matching": {"max_ratio": options.max_ratio, "cross_check": options.cross_check,
                     "rig_verification": options.resolved_rig_verification, "max_error_px": options.max_error_px,
                     "max_homography_inlier_ratio": options.max_homography_inlier_ratio},
    }


def drop_stale_work(database_path: Path, settings_path: Path, options: MatchingOptions) -> list[str]:
    """Clear the features and matches a resumed workspace made with other settings than ``options``, so a
    changed option takes effect instead of being silently ignored; records the settings. Returns what was
    cleared (``"features"``, ``"matches"``)."""
    now = _settings(options)
    before = now
    if settings_path.exists():
        try:
            before = json.loads(settings_path.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError):
            logger.warning("%s is unreadable: the features and matches are recomputed", settings_path)
            before = {}
        if not isinstance(before, dict):
            before = {}
    cleared = []
    if before != now:
        with open_database(database_path) as database:
            if before.get("features") != now["features"]:
                database.clear_keypoints()
                database.clear_descriptors()
                cleared.append("features")
            database.clear_matches()
            database.clear_two_view_geometries()
            cleared.append("matches")
        changed = [f"{key}: {before.get(group, {}).get(key)} -> {value}" for group in now
                   for key, value in now[group].items() if before.get(group, {}).get(key) != value]
        logger.warning("Settings changed since this workspace's last run (%s): recomputing its %s",
                       ", ".join(changed), " and ".join(cleared))
    write_json_atomic(settings_path, now)
    return cleared


def featured_images(images: Sequence[ImageEntry], options: MatchingOptions) -> list[ImageEntry]:
    return [e for e in images if e.sensor == "wide" or options.narrow_features]


def extract_features(
    database_path: Path,
    image_dir: Path,
    images: Sequence[ImageEntry],
    options: MatchingOptions,
    progress: Progress | None = None,
    batch_size: int = 2,
    *,
    num_threads: int = -1,
) -> int:
    """Extract SIFT (or ASIFT) for every image without keypoints yet; returns how many were extracted."""
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        todo = [
            e.name for e in featured_images(images, options) if not database.exists_keypoints(ids[e.name])
        ]
    if options.features == Features.ASIFT:
        from rigsfm.run.asift import extract_asift

        extract_asift(database_path, image_dir, todo, options.max_num_features, progress)
        logger.info("Extracted ASIFT for %d images (%d already done)", len(todo), len(images) - len(todo))
        return len(todo)
    extraction = pycolmap.FeatureExtractionOptions(num_threads=num_threads, use_gpu=False)
    extraction.sift.max_num_features = options.max_num_features
    for start in range(0, len(todo), batch_size):
        batch = todo[start : start + batch_size]
        pycolmap.extract_features(
            database_path,
            image_dir,
            image_names=batch,
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            extraction_options=extraction,
        )
        if progress:
            progress(start + len(batch), len(todo))
    logger.info("Extracted features for %d images (%d already done)", len(todo), len(images) - len(todo))
    return len(todo)


def image_pairs(images: Sequence[ImageEntry], options: MatchingOptions) -> list[tuple[str, str]]:
    """Every pair of featured images, except two images of the same frame without narrow features."""
    featured = featured_images(images, options)
    return [
        (a.name, b.name)
        for a, b in itertools.combinations(featured, 2)
        if not (a.rig == b.rig and a.frame == b.frame and not options.narrow_features)
    ]


def match_features(
    database_path: Path,
    images: Sequence[ImageEntry],
    options: MatchingOptions,
    pairs_path: Path,
    progress: Progress | None = None,
    batch_size: int = 6,
    *,
    num_threads: int = -1,
) -> int:
    """Match and verify every pair not verified yet; returns how many pairs were matched now."""
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        todo = [
            (a, b) for a, b in image_pairs(images, options) if not database.exists_two_view_geometry(ids[a], ids[b])
        ]
    matching = pycolmap.FeatureMatchingOptions(
        num_threads=num_threads, use_gpu=False, rig_verification=options.resolved_rig_verification
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
    for start in range(0, len(plain), batch_size):
        batch = plain[start : start + batch_size]
        pairs_path.write_text("".join(f"{a} {b}\n" for a, b in batch))
        pycolmap.match_image_pairs(
            database_path,
            matching_options=matching,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
            verification_options=verification,
        )
        if progress:
            progress(start + len(batch), len(todo))
    if direct:
        match_pairs_directly(database_path, direct, matching, verification,
                             (lambda done, _: progress(len(plain) + done, len(todo))) if progress else None)
        if matching.rig_verification:  # an empty pairs file: COLMAP's matcher then only runs its rig verification
            pairs_path.write_text("")
            pycolmap.match_image_pairs(
                database_path,
                matching_options=matching,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
                verification_options=verification,
            )
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
    one). Two passes of min (argpartition is ~20x slower here); ``squared`` is restored afterwards."""
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
