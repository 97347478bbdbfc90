"""Stage 2: SIFT features and matching with geometric verification.

Wide images always get features. Narrow images stay featureless unless ``narrow_features`` (their view
is homogeneous by design; features there only cost time and add outliers). Work already in the database
(keypoints of an image, a verified pair) is kept, so an interrupted run resumes where it stopped; work
made with other settings is cleared first (``drop_stale_work``), and so is the work of every image whose file's
content is not what it was made from (``drop_changed_images``: a new recording copied over the same names).

Extraction runs on this machine with pycolmap's threads, or one task per image on a Ray cluster
(``executor="ray"``, :mod:`rigsfm.core.executors`); both read the image with COLMAP's reader and run the
same extractor, so the features are bit-identical.

Which pairs are matched (:func:`select_pairs`): every pair of featured images (``Pairs.EXHAUSTIVE``,
quadratic), or (``Pairs.AUTO``) the pairs a cheap first pass finds worth it: the
``FIRST_PASS_FEATURES`` largest-scale SIFT features of every image (the ones a low-resolution image would
give; already extracted, so the pass costs no extraction) are matched between every pair (mutual nearest
neighbours passing the ratio test, one matrix product per image), and each image keeps its
``neighbours`` best-scoring partners of other rigs, plus a maximum spanning tree of the rigs (the network
stays connected), plus the pairs inside a rig (its wide and narrow image of a frame, consecutive frames).
With narrow features, the narrow images of each rig's ``NARROW_NEIGHBOURS`` best wide partners are matched
too; other pairs with a narrow image need a first-pass score of ``MIN_NARROW_SCORE``: a wide and a narrow
image of two different rigs (4x the focal length) almost never verify (12 textured rigs: 1 of 132 pairs, 16
inliers) and each costs a full matching. After
mapping, :func:`missed_pairs` checks the skipped pairs against the model (a warning if one would have
shared many points).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import sqlite3
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.executors import Executor, map_unordered
from rigsfm.core.geometry import project_world
from rigsfm.core.graph import DisjointSets
from rigsfm.core.io import file_sha256, write_json_atomic
from rigsfm.core.names import ImageName
from rigsfm.core.workspace import os_error_text
from rigsfm.run.inputs.database import open_database
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.matching.feature_cache import FeatureCache, features_from_cache, features_to_cache
from rigsfm.run.matching.gpu import use_gpu
from rigsfm.run.options import Features, MatchingOptions, Pairs

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


COARSE_SIFT_MIN_SIDE_PX = 1200  # images at least this large (longer side) ...
COARSE_SIFT_MIN_FRAMES = 8  # ... in networks of at least this many wide frames skip SIFT's upsampled octave


def resolved_first_octave(database_path: Path, images: Sequence[ImageEntry], options: MatchingOptions) -> int:
    """SIFT's first octave: ``options.first_octave``, or when None, 0 for a network of at least
    ``COARSE_SIFT_MIN_FRAMES`` wide frames whose wide images are at least ``COARSE_SIFT_MIN_SIDE_PX`` on their
    longer side, else -1 (COLMAP's default).

    At 16 rigs of 1624x1234 images, octave 0 took 16 instead of 54 CPU seconds to extract (5.5k instead of
    12.6k keypoints per image), matching 7 instead of 23, peak memory 480 instead of 1370 MB; the narrow
    errors were 3-5 % larger (rotation 0.106 vs 0.103 deg, distance 0.246 vs 0.235 %). Small networks and small
    images keep every feature: they are cheap, and wide separations need every match."""
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


def _settings(options: MatchingOptions, first_octave: int = -1) -> dict:
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


def drop_stale_work(database_path: Path, settings_path: Path, options: MatchingOptions,
                    first_octave: int = -1) -> list[str]:
    """Clear the features and matches a resumed workspace made with other settings than ``options`` (and
    ``first_octave``, :func:`resolved_first_octave`), so a changed option takes effect instead of being silently
    ignored; records the settings. Returns what was cleared (``"features"``, ``"matches"``)."""
    now = _settings(options, first_octave)
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


def image_digests(images: Sequence[ImageEntry]) -> dict[str, str]:
    """Per image name, the SHA-256 of its file (the feature cache's hash, :func:`rigsfm.core.io.file_sha256`)."""
    contents = {}
    for entry in images:
        try:
            contents[entry.name] = file_sha256(entry.path)
        except OSError as error:
            raise InputError(f"cannot read {entry.path}: {os_error_text(error)}; check the image folder") from None
    return contents


def _recorded_contents(record_path: Path) -> dict[str, str]:
    """The record :func:`drop_changed_images` wrote ({} when missing or unreadable: nothing is then trusted)."""
    try:
        data = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (ValueError, UnicodeDecodeError):
        logger.warning("%s is unreadable: every image's features and matches are made again", record_path)
        return {}
    contents = data.get("sha256") if isinstance(data, dict) else None
    return {k: v for k, v in contents.items() if isinstance(v, str)} if isinstance(contents, dict) else {}


def drop_changed_images(database_path: Path, record_path: Path, images: Sequence[ImageEntry]) -> list[str]:
    """Clear the features and matches of every image whose file is not the one they were made from (a new
    recording copied over the same names), so that the run works on the images it is given; records each image's
    content (:func:`image_digests`) in ``record_path``. Work in the database for an image the record does not
    name (a workspace of an older rigsfm, a removed record) is cleared too: what it was made from is unknown.
    Unchanged images keep their work. Returns the names whose work was cleared."""
    now = image_digests(images)
    before = _recorded_contents(record_path)
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        paired: dict[int, list[int]] = {}  # image id -> the ids it has matches or a two-view geometry with
        for pair_ids in (database.read_num_matches()[0], database.read_two_view_geometry_num_inliers()[0]):
            for pair_id in pair_ids:
                id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
                paired.setdefault(id1, []).append(id2)
                paired.setdefault(id2, []).append(id1)
        stale = [name for name, digest in now.items() if before.get(name) != digest and name in ids
                 and (database.exists_keypoints(ids[name]) or database.exists_descriptors(ids[name])
                      or ids[name] in paired)]
        if stale:
            with pycolmap.DatabaseTransaction(database):
                for name in stale:
                    for other in set(paired.get(ids[name], ())):
                        if database.exists_matches(ids[name], other):
                            database.delete_matches(ids[name], other)
                        if database.exists_two_view_geometry(ids[name], other):
                            database.delete_two_view_geometry(ids[name], other)
    if stale:
        _delete_features(database_path, [ids[name] for name in stale])
        changed = [name for name in stale if name in before]
        unknown = [name for name in stale if name not in before]
        if changed:
            logger.warning("%s changed since the last run in this workspace (%s): %s made again", _count(changed),
                           _names(changed), "its features and matches are" if len(changed) == 1 else
                           "their features and matches are")
        if unknown:
            logger.warning("%s holds no record of what the features and matches of %s were made from (%s): they "
                           "are made again", record_path, _count(unknown), _names(unknown))
    write_json_atomic(record_path, {"sha256": now})
    return stale


def _count(names: Sequence[str]) -> str:
    return f"{len(names)} image{'s' if len(names) != 1 else ''}"


def _names(names: Sequence[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def _delete_features(database_path: Path, image_ids: Sequence[int]) -> None:
    """Remove these images' keypoints and descriptors in one transaction (pycolmap's Database deletes only a
    table's every row; extraction then finds them without features)."""
    rows = [(int(image_id),) for image_id in image_ids]
    try:
        with contextlib.closing(sqlite3.connect(database_path)) as connection, connection:
            connection.executemany("DELETE FROM keypoints WHERE image_id = ?", rows)
            connection.executemany("DELETE FROM descriptors WHERE image_id = ?", rows)
    except sqlite3.OperationalError as error:  # as COLMAP's own errors: a full disk is named by disk_errors_named
        raise RuntimeError(f"{database_path}: {error}") from None


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
    device = pycolmap.Device.cuda if extraction.use_gpu else pycolmap.Device.cpu
    keypoints, descriptors = pycolmap.FeatureExtractor.create(extraction, device).extract(bitmap)
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
        todo = [
            e.name for e in featured_images(images, options) if not database.exists_keypoints(ids[e.name])
        ]
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
        )
        if progress:
            progress(start + len(batch), len(todo))


def image_pairs(images: Sequence[ImageEntry], options: MatchingOptions) -> list[tuple[str, str]]:
    """Every pair of featured images, except two images of the same frame without narrow features, and, with
    ``options.frame_offsets``, two narrow images of different rigs taken at different times."""
    featured = featured_images(images, options)
    times = narrow_times(images, options.frame_offsets)
    return [
        (a.name, b.name)
        for a, b in itertools.combinations(featured, 2)
        if not (a.rig == b.rig and a.frame == b.frame and not options.narrow_features)
        and not unsynchronised_pair(a, b, times)
    ]


def narrow_times(images: Sequence[ImageEntry], offsets: dict[str, int] | None) -> dict[str, int] | None:
    """Narrow image name -> its time in frames (its rig's k-th narrow frame at k + offset, rigsfm.run.checks.sync);
    None without offsets."""
    if offsets is None:
        return None
    frames: dict[str, list[ImageEntry]] = {}
    for entry in sorted(images, key=lambda e: e.frame):
        if entry.sensor == "narrow":
            frames.setdefault(entry.rig, []).append(entry)
    return {e.name: k + int(offsets.get(rig, 0)) for rig, entries in frames.items() for k, e in enumerate(entries)}


def unsynchronised_pair(a: ImageEntry, b: ImageEntry, times: dict[str, int] | None) -> bool:
    """Two narrow images of different rigs taken at different times: a moving crowd in them is not one scene."""
    return (times is not None and a.sensor == b.sensor == "narrow" and a.rig != b.rig
            and times.get(a.name) != times.get(b.name))


def drop_unsynchronised_pairs(database_path: Path, images: Sequence[ImageEntry],
                              offsets: dict[str, int] | None) -> int:
    """Delete the matches of narrow pairs of two rigs taken at different times (an earlier run's, made before the
    frame offsets were given); returns how many pairs were dropped."""
    times = narrow_times(images, offsets)
    if times is None:
        return 0
    narrow = [e for e in images if e.sensor == "narrow"]
    dropped = 0
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        for a, b in itertools.combinations(narrow, 2):
            if a.name in ids and b.name in ids and unsynchronised_pair(a, b, times) \
                    and database.exists_two_view_geometry(ids[a.name], ids[b.name]):
                database.delete_two_view_geometry(ids[a.name], ids[b.name])
                database.delete_matches(ids[a.name], ids[b.name])
                dropped += 1
    if dropped:
        logger.info("Dropped the matches of %d narrow pairs taken at different times (frame offsets)", dropped)
    return dropped


FIRST_PASS_FEATURES = 256  # largest-scale features per image matched in the first pass
MIN_NARROW_SCORE = 12  # first-pass matches a pair with a narrow image needs (random pairs score 2-8)
NARROW_NEIGHBOURS = 2  # with narrow features: narrow pairs of each rig's best wide partners, always matched


@dataclass
class PairSelection:
    """The pairs to match fully, out of every candidate pair, and why."""

    mode: Pairs
    pairs: list[tuple[str, str]]  # to match, in matching order
    num_candidates: int  # every pair exhaustive matching would match
    scores: dict[tuple[str, str], int] = field(default_factory=dict)  # first-pass matches per candidate (auto)
    first_pass_s: float = 0.0

    @property
    def skipped(self) -> list[tuple[str, str]]:
        chosen = set(self.pairs)
        return [pair for pair in self.scores if pair not in chosen]

    def summary(self) -> dict:
        return {"mode": str(self.mode), "candidates": self.num_candidates, "matched": len(self.pairs),
                "skipped": self.num_candidates - len(self.pairs), "first_pass_s": round(self.first_pass_s, 3)}


def first_pass_descriptors(database_path: Path, names: Sequence[str],
                           num_features: int = FIRST_PASS_FEATURES) -> dict[str, np.ndarray]:
    """Per image, its ``num_features`` largest-scale SIFT descriptors, unit length (float32)."""
    result = {}
    with open_database(database_path) as database:
        for name in names:
            # the images were just written
            image_id = database.read_image_with_name(name).image_id  # type: ignore[union-attr]
            keypoints = database.read_keypoints(image_id)
            descriptors = database.read_descriptors(image_id).data
            if len(keypoints) == 0:
                result[name] = np.zeros((0, 128), np.float32)
                continue
            scale = np.abs(keypoints[:, 2] * keypoints[:, 5] - keypoints[:, 3] * keypoints[:, 4])
            chosen = np.argsort(-scale, kind="stable")[:num_features]
            x = descriptors[chosen].astype(np.float32)
            result[name] = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    return result


def first_pass_scores(descriptors: dict[str, np.ndarray], pairs: Sequence[tuple[str, str]],
                      max_ratio: float = 0.8) -> dict[tuple[str, str], int]:
    """Mutual nearest neighbours passing the ratio test between the first-pass descriptors of each pair.

    One matrix product per image against all its partners (padded to the same number of features)."""
    partners: dict[str, list[str]] = {}
    for a, b in pairs:
        partners.setdefault(a, []).append(b)
    size = max((len(d) for d in descriptors.values()), default=0)
    if size < 2:
        return {pair: 0 for pair in pairs}

    def padded(name: str) -> np.ndarray:
        d = descriptors[name]
        return np.vstack([d, np.zeros((size - len(d), d.shape[1]), np.float32)]) if len(d) < size else d

    scores = {}
    for a, others in partners.items():
        da = descriptors[a]
        if len(da) < 2:
            scores.update({(a, b): 0 for b in others})
            continue
        block = np.stack([padded(b) for b in others])  # (P, size, 128)
        similarity = np.einsum("id,pjd->pij", da, block)  # (P, n_a, size)
        valid = np.array([len(descriptors[b]) for b in others])
        padding = np.arange(size)[None, None, :] >= valid[:, None, None]
        similarity = np.where(padding, np.float32(-2.0), similarity)  # padding never matches
        top2 = -np.partition(-similarity, 1, axis=2)[:, :, :2]  # best, second best similarity
        distance = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * top2))
        ratio_ok = distance[:, :, 0] < max_ratio * distance[:, :, 1]
        best_in_b = similarity.argmax(axis=2)  # (P, n_a)
        best_in_a = similarity.argmax(axis=1)  # (P, size)
        mutual = np.take_along_axis(best_in_a, best_in_b, axis=1) == np.arange(len(da))[None, :]
        counts = (ratio_ok & mutual).sum(axis=1)
        scores.update({(a, b): int(c) for b, c in zip(others, counts)})
    return {pair: scores[pair] for pair in pairs}


def _spanning_tree(nodes: Sequence[str], edges: dict[tuple[str, str], float]) -> list[tuple[str, str]]:
    """Maximum spanning forest (Kruskal) of ``nodes`` under ``edges`` (pair -> weight)."""
    sets = DisjointSets(nodes)
    return [(a, b) for (a, b), _ in sorted(edges.items(), key=lambda item: (-item[1], item[0])) if sets.union(a, b)]


def select_pairs(database_path: Path, images: Sequence[ImageEntry], options: MatchingOptions) -> PairSelection:
    """The pairs to match (see the module docstring): every candidate, or the first pass's choice."""
    import time

    candidates = image_pairs(images, options)
    if options.pairs == Pairs.EXHAUSTIVE:
        return PairSelection(Pairs.EXHAUSTIVE, candidates, len(candidates))
    start = time.perf_counter()
    entry = {e.name: e for e in images}
    featured = [e.name for e in featured_images(images, options)]
    frames = {rig: sorted({e.frame for e in images if e.rig == rig}) for rig in {e.rig for e in images}}

    def inside_rig(a: str, b: str) -> bool:  # a frame's wide and narrow image, or consecutive frames
        ea, eb = entry[a], entry[b]
        if ea.frame == eb.frame:
            return True
        order = frames[ea.rig]
        return ea.sensor == eb.sensor and abs(order.index(ea.frame) - order.index(eb.frame)) == 1

    keep = {pair for pair in candidates if entry[pair[0]].rig == entry[pair[1]].rig and inside_rig(*pair)}
    between = [pair for pair in candidates if entry[pair[0]].rig != entry[pair[1]].rig]
    scores = first_pass_scores(first_pass_descriptors(database_path, featured), between, options.max_ratio)
    ranked: dict[str, list[tuple[int, str, tuple[str, str]]]] = {}
    for pair, score in scores.items():
        wide_only = entry[pair[0]].sensor == entry[pair[1]].sensor == "wide"
        if not wide_only and score < MIN_NARROW_SCORE:
            continue
        for one, other in (pair, pair[::-1]):
            ranked.setdefault(one, []).append((-score, other, pair))
    for partners in ranked.values():
        keep.update(pair for _, _, pair in sorted(partners)[: options.neighbours])
    # The narrow images of neighbouring rigs see the same crowd from close directions: match them for the
    # NARROW_NEIGHBOURS best wide partners of each wide image (12 textured rigs: the 12 narrow pairs of adjacent
    # rigs were the only narrow pairs that verified, 57 inliers each; without them the narrow distance error
    # was 1.29x).
    narrow_of = {(e.rig, e.frame): e.name for e in images if e.sensor == "narrow" and e.name in set(featured)}
    order_of = {pair: i for i, pair in enumerate(candidates)}
    for name, partners in ranked.items():
        if entry[name].sensor != "wide":
            continue
        wide_partners = [other for _, other, _ in sorted(partners) if entry[other].sensor == "wide"]
        for other in wide_partners[:NARROW_NEIGHBOURS]:
            a = narrow_of.get((entry[name].rig, entry[name].frame))
            b = narrow_of.get((entry[other].rig, entry[other].frame))
            if a and b and ((a, b) in order_of or (b, a) in order_of):  # not when taken at different times
                keep.add((a, b) if (a, b) in order_of else (b, a))
    rig_links: dict[tuple[str, str], tuple[int, tuple[str, str]]] = {}
    for pair, score in scores.items():
        if entry[pair[0]].sensor == entry[pair[1]].sensor == "wide":
            link = tuple(sorted((entry[pair[0]].rig, entry[pair[1]].rig)))
            if score > rig_links.get(link, (-1, None))[0]:  # type: ignore[arg-type]  # two rigs; (-1, None): none yet
                rig_links[link] = (score, pair)  # type: ignore[index]  # sorted: two rigs
    tree = _spanning_tree(sorted(frames), {link: score for link, (score, _) in rig_links.items()})
    keep.update(rig_links[link][1] for link in tree)
    pairs = sorted(keep, key=order_of.__getitem__)
    all_scores = {pair: scores.get(pair, -1) for pair in candidates}  # -1: inside a rig, not scored
    selection = PairSelection(Pairs.AUTO, pairs, len(candidates), all_scores, time.perf_counter() - start)
    logger.info("Pairs: %d of %d chosen by a first pass over %d images (%.1f s)", len(pairs), len(candidates),
                len(featured), selection.first_pass_s)
    return selection


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
    their indexes once: batches of 6 pairs cost 1.8x the CPU time of batches of 60 at 16 rigs)."""
    selection = selection or select_pairs(database_path, images, options)
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        todo = [(a, b) for a, b in selection.pairs if not database.exists_two_view_geometry(ids[a], ids[b])]
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


MISSED_MIN_POINTS = 50  # a skipped pair predicted to share fewer points is not worth a warning
# A skipped pair is missed when it beats the weakest matched pair of both its images by this factor: the
# predicted count is 1.3-2.5x a pair's verified inliers (16-rig circle, all 120 pairs), so a smaller margin
# flags the first pass's ordinary near-ties at the k-th partner.
MISSED_FACTOR = 2.0
MISSED_MAX_VIEW_ANGLE_DEG = 40.0  # SIFT rarely matches a point seen from directions further apart


@dataclass(frozen=True)
class MissedPair:
    image_a: str
    image_b: str
    predicted_points: int  # model points seen by one image that the other sees from a similar direction
    weakest_matched: int  # the same count for the weakest pair matched for either image


def _observed_points(reconstruction: pycolmap.Reconstruction, image: pycolmap.Image) -> np.ndarray:
    ids = [p.point3D_id for p in image.get_observation_points2D()]
    return np.array([reconstruction.point3D(i).xyz for i in ids]).reshape(-1, 3)


def covisible_points(reconstruction: pycolmap.Reconstruction, pairs: Sequence[tuple[str, str]]) -> list[int]:
    """Per pair of registered image names: the points of the model observed in one image that the other sees
    (in front, inside its image, from a viewing direction within ``MISSED_MAX_VIEW_ANGLE_DEG`` of the observing
    image's), the larger of the two counts. Batched per observing image: a 64-rig circle asks for ~8 000 pairs."""
    images = {im.name: im for im in reconstruction.images.values() if im.has_pose}
    partners: dict[str, list[str]] = {}
    for a, b in pairs:
        partners.setdefault(a, []).append(b)
        partners.setdefault(b, []).append(a)
    cos_max = np.cos(np.radians(MISSED_MAX_VIEW_ANGLE_DEG))
    seen_from: dict[tuple[str, str], int] = {}  # (observing image, other image) -> count
    for name, others in partners.items():
        xyz = _observed_points(reconstruction, images[name])
        ray = xyz - images[name].projection_center()
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        to_points = xyz[None] - np.array([images[o].projection_center() for o in others])[:, None]  # (M, N, 3)
        cosine = np.einsum("nk,mnk->mn", ray, to_points) / np.linalg.norm(to_points, axis=2)
        for other, close in zip(others, cosine > cos_max):
            count = 0
            if close.any():  # (most pairs of a large circle: no point within the angle)
                camera = reconstruction.cameras[images[other].camera_id]
                count = int(np.sum(project_world(camera, images[other].cam_from_world(), xyz[close])[1]))
            seen_from[(name, other)] = count
    return [max(seen_from[(a, b)], seen_from[(b, a)]) for a, b in pairs]


def missed_pairs(reconstruction: pycolmap.Reconstruction, selection: PairSelection) -> list[MissedPair]:
    """Skipped pairs of registered images that the final model says would have shared many points: at least
    ``MISSED_MIN_POINTS`` and ``MISSED_FACTOR`` x the weakest pair matched for each of its images with a partner
    of the same sensor (by the same count, :func:`covisible_points`; matched pairs under ``MISSED_MIN_POINTS``
    do not count). Pairs of a wide and a narrow image of two
    rigs are not checked: the shared points the model predicts say nothing of a 4x change of scale."""
    if selection.mode != Pairs.AUTO or not selection.skipped:
        return []
    posed = {im.name: im for im in reconstruction.images.values() if im.has_pose}
    matched = [(a, b) for a, b in selection.pairs if a in posed and b in posed
               and ImageName.parse(a).rig != ImageName.parse(b).rig]
    sensor = {name: ImageName.parse(name).sensor for name in posed}
    # Wide and narrow images of two rigs are 4x the scale apart: SIFT rarely matches them, and the first pass
    # found too few matches (MIN_NARROW_SCORE); their skipped pairs are not checked.
    skipped = [(a, b) for a, b in selection.skipped if a in posed and b in posed and sensor[a] == sensor[b]
               and ImageName.parse(a).rig != ImageName.parse(b).rig]
    counts = covisible_points(reconstruction, matched + skipped)
    weakest: dict[tuple[str, str], int] = {}  # (image, sensor of the partner) -> weakest matched pair's count
    for (a, b), shared in zip(matched, counts):
        if shared < MISSED_MIN_POINTS:  # matched but sharing nothing in the model: no measure of the cut
            continue
        for one, other in ((a, b), (b, a)):
            key = (one, sensor[other])
            weakest[key] = min(weakest.get(key, shared), shared)
    missed = []
    for (a, b), shared in zip(skipped, counts[len(matched):]):
        bar = max(weakest.get((a, sensor[b]), 0), weakest.get((b, sensor[a]), 0))
        if shared >= MISSED_MIN_POINTS and shared > MISSED_FACTOR * bar:
            missed.append(MissedPair(a, b, shared, bar))
    return sorted(missed, key=lambda m: -m.predicted_points)


def pairs_report(reconstruction: pycolmap.Reconstruction, selection: PairSelection) -> tuple[dict, str | None]:
    """summary.json's ``pairs`` (counts, first-pass time, missed pairs) and a warning when pairs were missed."""
    missed = missed_pairs(reconstruction, selection)
    report = {**selection.summary(), "missed": [vars(m) for m in missed[:20]], "num_missed": len(missed)}
    if not missed:
        return report, None
    worst = missed[0]
    return report, (f"PAIRS MISSED: {len(missed)} skipped image pair(s) would have shared points by the final model "
                    f"(e.g. {worst.image_a} - {worst.image_b}: ~{worst.predicted_points} points, more than the "
                    f"weakest matched pair's {worst.weakest_matched}); re-run with --pairs exhaustive or a larger "
                    f"--neighbours")
