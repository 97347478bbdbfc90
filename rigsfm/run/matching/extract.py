"""Stage 3, features: SIFT features (SIFT or ASIFT), on this machine or a Ray cluster.

Wide images always get features. Narrow images stay featureless unless ``narrow_features`` (their view
is homogeneous by design; features there only cost time and add outliers). Work already in the database
(keypoints of an image, a verified pair) is kept, so an interrupted run resumes where it stopped (``reuse``).

Extraction runs on this machine with pycolmap's threads, or one task per image on a Ray cluster
(``executor="ray"``, :mod:`rigsfm.core.executors`); both read the image with COLMAP's reader and run the
same extractor, so the features are bit-identical.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.executors import Executor, map_unordered
from rigsfm.run.inputs.database import open_database
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.matching.feature_cache import FeatureCache, features_from_cache, features_to_cache
from rigsfm.run.matching.gpu import pycolmap_device, use_gpu
from rigsfm.run.options import Features, MatchingOptions, Pairs

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


COARSE_SIFT_MIN_SIDE_PX = 1200  # images at least this large (longer side) ...
COARSE_SIFT_MIN_FRAMES = 8  # ... in networks of at least this many wide frames skip SIFT's upsampled octave


def resolved_first_octave(database_path: Path, images: Sequence[ImageEntry], options: MatchingOptions) -> int:
    """SIFT's first octave: ``options.first_octave``, or when None, 0 for a network of at least
    ``COARSE_SIFT_MIN_FRAMES`` wide frames whose wide images are at least ``COARSE_SIFT_MIN_SIDE_PX`` on their
    longer side, else -1 (COLMAP's default).

    On large networks of large images octave 0 costs a fraction of the extraction and matching time and memory
    for slightly larger narrow errors (see benchmarks/README.md). Small networks and small images keep every
    feature: they are cheap, and wide separations need every match."""
    if options.first_octave is not None:
        return options.first_octave
    wide = [e.name for e in images if e.sensor == "wide"]
    if len(wide) < COARSE_SIFT_MIN_FRAMES:
        return -1
    with open_database(database_path) as database:
        cameras = {c.camera_id: c for c in database.read_all_cameras()}
        # the images were just written
        sides = [max(cameras[database.read_image_with_name(n).camera_id].width,  # type: ignore[union-attr]
                     cameras[database.read_image_with_name(n).camera_id].height) for n in wide]  # type: ignore[union-attr]
    return 0 if min(sides) >= COARSE_SIFT_MIN_SIDE_PX else -1


def work_settings(options: MatchingOptions, first_octave: int = -1) -> dict:
    """What the stored features and matches depend on (threads do not count)."""
    settings = {
        "features": {"type": str(options.features), "max_num_features": options.max_num_features,
                     "narrow_features": options.narrow_features},
        "matching": {"max_ratio": options.max_ratio, "cross_check": options.cross_check,
                     "rig_verification": options.resolved_rig_verification, "max_error_px": options.max_error_px,
                     "max_homography_inlier_ratio": options.max_homography_inlier_ratio,
                     "pairs": str(options.pairs),
                     "neighbours": options.neighbours if options.pairs == Pairs.AUTO else None},
    }
    if first_octave != -1:  # recorded only when not COLMAP's default, so older workspaces resume
        settings["features"]["first_octave"] = first_octave
    if use_gpu(options.device):  # GPU SIFT gives other features and matches than the CPU's
        settings["features"]["device"] = settings["matching"]["device"] = "cuda"
    return settings


def featured_images(images: Sequence[ImageEntry], options: MatchingOptions) -> list[ImageEntry]:
    return [e for e in images if e.sensor == "wide" or options.narrow_features]


def _extraction_options(options: MatchingOptions, num_threads: int,
                        first_octave: int = -1) -> pycolmap.FeatureExtractionOptions:
    gpu = use_gpu(options.device)
    extraction = pycolmap.FeatureExtractionOptions(num_threads=num_threads, use_gpu=gpu)
    extraction.sift.max_num_features = options.max_num_features
    extraction.sift.first_octave = first_octave
    return extraction


@dataclass(frozen=True)
class ImageFeatures:
    """One image's SIFT features, as the database stores them."""

    name: str
    keypoints: np.ndarray  # (N, 6) float32: x, y, a11, a12, a21, a22 (COLMAP pixels)
    descriptors: np.ndarray  # (N, 128) uint8


def extract_one(task: tuple[str, bytes, str], extraction: pycolmap.FeatureExtractionOptions) -> ImageFeatures:
    """SIFT of one image given as its file's bytes (a Ray task): read with COLMAP's own image reader (from
    a temporary file with the same suffix) and scaled down beyond ``max_image_size`` (``Bitmap.thumbnail``,
    keypoints scaled back per axis) exactly as ``pycolmap.extract_features`` does, so the result is
    bit-identical to a local extraction (tested, also for a scaled-down image)."""
    name, data, suffix = task
    with tempfile.TemporaryDirectory(prefix="rigsfm-sift-") as folder:
        path = Path(folder) / f"image{suffix}"
        path.write_bytes(data)
        bitmap = pycolmap.Bitmap.read(path, as_rgb=False)
    if bitmap is None:
        raise InputError(f"cannot decode {name}")
    width, height = bitmap.width, bitmap.height
    limit = extraction.eff_max_image_size()
    if limit > 0:
        bitmap.thumbnail(limit)  # what COLMAP's image reader does beyond max_image_size (bilinear)
    scale_x, scale_y = width / bitmap.width, height / bitmap.height  # back to the file's pixels, as COLMAP
    keypoints, descriptors = pycolmap.FeatureExtractor.create(
        extraction, pycolmap_device(extraction.use_gpu)).extract(bitmap)
    rows = []
    for keypoint in keypoints:
        if scale_x != 1.0 or scale_y != 1.0:
            keypoint.rescale(scale_x, scale_y)
        rows.append((keypoint.x, keypoint.y, keypoint.a11, keypoint.a12, keypoint.a21, keypoint.a22))
    array = np.array(rows, dtype=np.float32).reshape(-1, 6)
    return ImageFeatures(name, array, np.ascontiguousarray(descriptors.data, dtype=np.uint8))


def _read_for_ray(task: tuple[str, Path]) -> tuple[str, bytes, str]:
    name, path = task
    try:
        return name, Path(path).read_bytes(), Path(path).suffix
    except OSError as e:
        raise InputError(f"cannot read {path}: {e}") from e


def extract_features(
    database_path: Path,
    image_dir: Path,
    images: Sequence[ImageEntry],
    options: MatchingOptions,
    progress: Progress | None = None,
    batch_size: int = 8,
    *,
    num_threads: int = -1,
    executor: str = Executor.LOCAL,
    address: str | None = None,
    workers: int = 2,
) -> int:
    """Extract SIFT (or ASIFT) for every image without keypoints yet; returns how many images got features.

    ``executor="ray"``: one task per image on the Ray cluster at ``address`` (or a local Ray instance with
    ``workers`` CPUs); the images travel as bytes, the features come back and are written here. With
    ``RIGSFM_FEATURE_CACHE`` set, features of the same image file and settings come from that cache
    (:mod:`rigsfm.run.matching.feature_cache`) and new ones are added to it."""
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        featured = [e.name for e in featured_images(images, options)]
        todo = [name for name in featured if not database.exists_keypoints(ids[name])]
    if progress and not todo:  # every image's features kept from before: the stage is done, not still counting
        progress(len(featured), len(featured))
    first_octave = resolved_first_octave(database_path, images, options)
    paths = {e.name: e.path for e in images}
    cache = FeatureCache.from_environment(_cache_settings(options, first_octave))
    extract, entries = todo, {}
    if cache is not None and todo:
        entries = {name: cache.entry(paths[name]) for name in todo}  # each image file read once for its key
        with open_database(database_path) as database:
            extract = features_from_cache(database, cache, entries, ids)
    cached = len(todo) - len(extract)
    if progress and cached:
        progress(cached, len(todo))
    if extract:
        shifted = (lambda done, _: progress(cached + done, len(todo))) if progress else None
        _extract(database_path, image_dir, paths, ids, extract, options, first_octave, shifted, batch_size,
                 num_threads, executor, address, workers)
        if cache is not None:
            with open_database(database_path) as database:
                features_to_cache(database, cache, entries, ids, extract)
    logger.info("Features for %d images: %d extracted, %d from the feature cache (%d already done)", len(todo),
                len(extract), cached, len(images) - len(todo))
    return len(todo)


def _cache_settings(options: MatchingOptions, first_octave: int) -> dict:
    """What an image's features depend on besides its file (rigsfm.run.matching.feature_cache's key)."""
    if options.features == Features.ASIFT:
        return {"features": str(options.features), "max_num_features": options.max_num_features}
    extraction = _extraction_options(options, num_threads=1, first_octave=first_octave).todict()
    for threads in ("num_threads", "gpu_index"):
        extraction.pop(threads, None)
    return {"features": str(options.features), "extraction": extraction}


def _extract(database_path: Path, image_dir: Path, paths: dict[str, Path], ids: dict[str, int], todo: list[str],
             options: MatchingOptions, first_octave: int, progress: Progress | None, batch_size: int,
             num_threads: int, executor: str, address: str | None, workers: int) -> None:
    if options.features == Features.ASIFT:
        from rigsfm.run.matching.asift import extract_asift

        extract_asift(database_path, image_dir, todo, options.max_num_features, progress)
        return
    if executor == Executor.RAY:
        extraction = _extraction_options(options, num_threads=1, first_octave=first_octave)
        done = [0]
        with open_database(database_path) as database:
            def write(features: ImageFeatures) -> None:
                image_id = ids[features.name]
                database.write_keypoints(image_id, features.keypoints)
                database.write_descriptors(
                    image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, features.descriptors))
                done[0] += 1
                if progress:
                    progress(done[0], len(todo))

            map_unordered(extract_one, [(name, paths[name]) for name in todo], write, executor=executor,
                          workers=workers, address=address, shared=(extraction,), prepare=_read_for_ray)
        logger.info("Extracted features for %d images on Ray", len(todo))
        return
    extraction = _extraction_options(options, num_threads, first_octave)
    logger.info("SIFT from octave %d", first_octave)
    for start in range(0, len(todo), batch_size):
        batch = todo[start : start + batch_size]
        pycolmap.extract_features(
            database_path,
            image_dir,
            image_names=batch,
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            extraction_options=extraction,
            device=pycolmap_device(extraction.use_gpu),
        )
        if progress:
            progress(start + len(batch), len(todo))
