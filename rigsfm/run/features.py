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

import pycolmap

from rigsfm.run.inputs import ImageEntry
from rigsfm.run.options import Features, MatchingOptions
from rigsfm.core.io import write_json_atomic

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
    before = json.loads(settings_path.read_text()) if settings_path.exists() else now
    cleared = []
    if before != now:
        with pycolmap.Database.open(database_path) as database:
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
    with pycolmap.Database.open(database_path) as database:
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
    with pycolmap.Database.open(database_path) as database:
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
    for start in range(0, len(todo), batch_size):
        batch = todo[start : start + batch_size]
        pairs_path.write_text("".join(f"{a} {b}\n" for a, b in batch))
        pycolmap.match_image_pairs(
            database_path,
            matching_options=matching,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
            verification_options=verification,
        )
        if progress:
            progress(start + len(batch), len(todo))
    pairs_path.unlink(missing_ok=True)
    logger.info("Matched %d image pairs", len(todo))
    return len(todo)
