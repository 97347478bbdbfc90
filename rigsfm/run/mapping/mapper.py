"""Stage 5, mapping: register the wide cameras with COLMAP's incremental or global mapper (``auto``, the default: the
global one from 16 wide frames, where it is faster at the same accuracy; the incremental one below).

Intrinsics and every ``sensor_from_rig`` (E^sl) stay fixed. Small networks (2-4 rigs) only have
two-view tracks, which COLMAP ignores by default; they are allowed here, and the model-size and
track-length minimums are lowered to what the network can provide. The incremental mapper starts from a
wide pair that COLMAP's own initial-pair test accepts (:func:`initial_pair`) and has a time limit, after
which the global mapper is used (with a warning).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import pycolmap

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.io import atomic_directory
from rigsfm.core.names import ImageName, Sensor
from rigsfm.core.workspace import Workspace, read_model
from rigsfm.run.inputs.database import open_database
from rigsfm.run.options import Mapper, MappingOptions

logger = logging.getLogger(__name__)


def _incremental_options(options: MappingOptions, num_wide: int, num_threads: int) -> pycolmap.IncrementalPipelineOptions:
    pipeline = pycolmap.IncrementalPipelineOptions(
        num_threads=num_threads,
        random_seed=options.seed,
        ba_refine_focal_length=False,
        ba_refine_principal_point=False,
        ba_refine_extra_params=False,
        ba_refine_sensor_from_rig=False,
        min_model_size=min(10, max(2, num_wide)),
        # One model: a forced initial pair would otherwise be re-used for every further model, and
        # frames the incremental mapper cannot reach are handed to the global mapper instead.
        multiple_models=False,
        extract_colors=True,
    )
    pipeline.mapper.abs_pose_refine_focal_length = False
    pipeline.mapper.abs_pose_refine_extra_params = False
    # Rigs far apart round an arena share many points between neighbours only: keep two-view tracks (verified,
    # and the adjustment drops outliers with a robust loss); they cost time and pay where the wide views share a
    # textured centre (see benchmarks/README.md).
    pipeline.triangulation.ignore_two_view_tracks = False
    return pipeline


def _global_options(options: MappingOptions, num_wide: int, num_threads: int) -> pycolmap.GlobalPipelineOptions:
    pipeline = pycolmap.GlobalPipelineOptions(
        num_threads=num_threads, random_seed=options.seed, min_model_size=min(3, max(2, num_wide))
    )
    mapper = pipeline.mapper
    mapper.num_threads = num_threads
    mapper.random_seed = options.seed
    mapper.refine_sensor_from_rig = False
    mapper.rotation_averaging.refine_sensor_from_rig = False
    mapper.global_positioning.refine_sensor_from_rig = False
    mapper.global_positioning.use_gpu = False
    mapper.bundle_adjustment.refine_focal_length = False
    mapper.bundle_adjustment.refine_principal_point = False
    mapper.bundle_adjustment.refine_extra_params = False
    mapper.bundle_adjustment.refine_sensor_from_rig = False
    mapper.bundle_adjustment.ceres.use_gpu = False
    # Positions from two-view tracks only where nothing else exists (2-4 rigs); the final adjustment and
    # retriangulation keep two-view tracks always, as the incremental mapper does.
    mapper.bundle_adjustment.min_track_length = 2
    mapper.retriangulation.ignore_two_view_tracks = False
    if num_wide <= 4:
        mapper.track_min_num_views_per_track = 2
        mapper.global_positioning.min_num_view_per_track = 2
    # Global positioning from the longest tracks, until each image has GLOBAL_TRACKS_PER_VIEW of them (COLMAP's
    # own selection; its default keeps all); bundle adjustment and retriangulation then use every match.
    mapper.track_required_tracks_per_view = GLOBAL_TRACKS_PER_VIEW
    return pipeline


# The global mapper keeps this many tracks per view: far faster global positioning on large circles, the same
# accuracy after the adjustment (see benchmarks/README.md, "Arena scale").
GLOBAL_TRACKS_PER_VIEW = 500


FEW_MATCHES_MIN_INLIERS = 8  # the least a pair of manual correspondences keeps (rigsfm.run.matching.manual_matches)


def relax_for_few_matches(pipeline: pycolmap.IncrementalPipelineOptions, best_inliers: int) -> None:
    """Thresholds for networks held together by few matches (e.g. ~30 manual correspondences).

    COLMAP ignores pairs under ``min_num_matches`` (15), starts only from a pair with
    ``init_min_num_inliers`` (100) and adds images with ``abs_pose_min_num_inliers`` (30).
    """
    floor = FEW_MATCHES_MIN_INLIERS
    pipeline.min_num_matches = min(pipeline.min_num_matches, floor)
    mapper = pipeline.mapper
    mapper.init_min_num_inliers = min(mapper.init_min_num_inliers, max(floor, best_inliers // 2))
    mapper.abs_pose_min_num_inliers = min(mapper.abs_pose_min_num_inliers, 2 * floor)
    # Rigs far apart round an arena face each other: the baseline runs along the optical axes, which
    # COLMAP's forward-motion guard (0.95) rejects although the points between them triangulate well.
    mapper.init_max_forward_motion = 1.0
    logger.info("Few matches (best wide pair %d inliers): min_num_matches %d, init_min_num_inliers %d, "
                "abs_pose_min_num_inliers %d, any forward motion", best_inliers, pipeline.min_num_matches,
                mapper.init_min_num_inliers, mapper.abs_pose_min_num_inliers)


@dataclass(frozen=True, order=True)
class WidePair:
    inliers: int
    image_id1: int
    image_id2: int
    label: str = field(compare=False)  # "rig01-rig03"


def wide_pairs(database: pycolmap.Database) -> list[WidePair]:
    """The verified wide-wide pairs of two different rigs, most inliers first."""
    names = {image.image_id: image.name for image in database.read_all_images()}
    pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    pairs = []
    for pair_id, count in zip(pair_ids, inliers):
        id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
        one, two = ImageName.parse(names[id1]), ImageName.parse(names[id2])
        if one.sensor == two.sensor == Sensor.WIDE and one.rig != two.rig:
            pairs.append(WidePair(int(count), int(id1), int(id2), f"{one.rig}-{two.rig}"))
    return sorted(pairs, reverse=True)


# COLMAP relaxes a failed initialisation twice by halving init_min_num_inliers, then init_min_tri_angle.
RELAXATIONS = ((1, 1), (2, 1), (2, 2), (4, 2), (4, 4))
MAX_INITIAL_PAIR_TESTS = 100  # each test is a two-view reconstruction: bound their time


def initial_pair(cache: pycolmap.DatabaseCache, pipeline: pycolmap.IncrementalPipelineOptions,
                 pairs: list[WidePair]) -> WidePair | None:
    """The wide pair of two rigs, most inliers first, that COLMAP's own initial-pair test accepts (inliers,
    forward motion, triangulation angle, the rigs' generalized relative pose) at the mapper's thresholds, or
    at the first of COLMAP's relaxations where one does; None if none does within MAX_INITIAL_PAIR_TESTS.

    The pair with the most inliers alone is often two neighbouring rigs whose matches lie on the (textured)
    ground: a homography, a median triangulation angle of ~3 deg, below even COLMAP's most relaxed minimum
    (4 deg), so forcing it failed 1000 times (200 trials x 5 relaxations), for minutes. Chosen here, the mapper
    also skips its own search, which can run for minutes when the narrow images carry many features.
    """
    start = time.perf_counter()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(pycolmap.Reconstruction())
    base = pipeline.get_mapper()
    tested = 0
    rejected: list = []
    try:
        for inlier_div, angle_div in RELAXATIONS:
            options = pipeline.get_mapper()
            options.init_min_num_inliers = base.init_min_num_inliers // inlier_div
            options.init_min_tri_angle = base.init_min_tri_angle / angle_div
            for pair in pairs:
                if tested == MAX_INITIAL_PAIR_TESTS:
                    break
                if pair.inliers < options.init_min_num_inliers:
                    continue
                if not (cache.exists_image(pair.image_id1) and cache.exists_image(pair.image_id2)):
                    continue
                tested += 1
                if mapper.estimate_initial_two_view_geometry(options, pair.image_id1, pair.image_id2) is not None:
                    logger.info("Initial pair %s (%d inliers; init_min_num_inliers %d, init_min_tri_angle %.3g deg); "
                                "%d pair(s) with more inliers fail COLMAP's initial-pair test (%s); %d tests in %.2f s",
                                pair.label, pair.inliers, options.init_min_num_inliers, options.init_min_tri_angle,
                                len(rejected), ", ".join(f"{r.label} ({r.inliers})" for r in rejected[:4]), tested,
                                time.perf_counter() - start)
                    return pair
                if pair not in rejected:
                    rejected.append(pair)
    finally:
        mapper.end_reconstruction(True)
    logger.info("No wide pair passes COLMAP's initial-pair test (%d tests in %.2f s); the mapper searches", tested,
                time.perf_counter() - start)
    return None


def _run_past_rig_scale_bug(run: Callable[[], None]) -> bool:
    """``run()`` (a mapper); True when it stopped at pycolmap 4.2.1's bug after mapping:
    ``AlignReconstructionToOrigRigScales`` looks up every rig whose narrow offset is non-zero and raises
    ``IndexError: Rig with ID n does not exist`` for a rig none of whose frames registered. The model is finished
    by then, and that alignment would change nothing here (sensor_from_rig is held fixed, so its scale ratio is
    1): the model is kept as it is."""
    try:
        run()
    except IndexError as error:
        if not str(error).startswith("Rig with ID"):
            raise
        logger.info("COLMAP's rig-scale alignment failed (%s); the model is kept as it is", error)
        return True
    return False


@dataclass
class _Run:
    models: list[pycolmap.Reconstruction]
    timed_out: bool = False  # the mapper stopped at its time limit: what it left is unfinished


def _run_incremental(cache: pycolmap.DatabaseCache, pipeline: pycolmap.IncrementalPipelineOptions,
                     deadline: float | None, on_registered: Callable[[], None] | None) -> _Run:
    if deadline is not None:
        remaining = deadline - time.monotonic()
        if remaining < 1:
            return _Run([], timed_out=True)
        pipeline.max_runtime_seconds = int(remaining)
    manager = pycolmap.ReconstructionManager()
    mapper = pycolmap.IncrementalPipeline(pipeline, cache, manager)
    if on_registered is not None:
        mapper.add_callback(pycolmap.IncrementalPipelineCallback.NEXT_IMAGE_REG_CALLBACK, on_registered)
    _run_past_rig_scale_bug(mapper.run)
    return _Run([manager.get(i) for i in range(manager.size())], timed_out=mapper.check_reached_max_runtime())


def _incremental(database_path: Path, image_dir: Path, options: MappingOptions, num_wide: int, num_threads: int,
                 on_registered: Callable[[], None] | None) -> _Run:
    limit = options.incremental_time_limit_s
    deadline = None if limit is None else time.monotonic() + limit
    pipeline = _incremental_options(options, num_wide, num_threads)
    pipeline.image_path = str(image_dir)
    with open_database(database_path) as database:
        pairs = wide_pairs(database)
        if options.few_matches:
            relax_for_few_matches(pipeline, pairs[0].inliers if pairs else 0)
        cache_options = pycolmap.DatabaseCacheOptions()
        cache_options.min_num_matches = pipeline.min_num_matches
        cache_options.ignore_watermarks = pipeline.ignore_watermarks
        cache = pycolmap.DatabaseCache.create(database, cache_options)
    pair = initial_pair(cache, pipeline, pairs)
    if pair is not None:
        search_trials = pipeline.init_num_trials
        pipeline.init_image_id1, pipeline.init_image_id2 = pair.image_id1, pair.image_id2
        pipeline.init_num_trials = 1  # COLMAP tries a given pair init_num_trials times; it fails alike each time
        run = _run_incremental(cache, pipeline, deadline, on_registered)
        if run.models or run.timed_out:
            return run
        logger.warning("Mapping from the initial pair %s failed; the mapper searches for another", pair.label)
        pipeline.init_image_id1 = pipeline.init_image_id2 = -1
        pipeline.init_num_trials = search_trials
    return _run_incremental(cache, pipeline, deadline, on_registered)


def _global(database_path: Path, image_dir: Path, options: MappingOptions, num_wide: int, num_threads: int) -> _Run:
    pipeline_options = _global_options(options, num_wide, num_threads)
    pipeline_options.image_path = str(image_dir)
    manager = pycolmap.ReconstructionManager()
    with open_database(database_path) as database:
        pipeline = pycolmap.GlobalPipeline(pipeline_options, database, manager)
        if _run_past_rig_scale_bug(pipeline.run):
            for i in range(manager.size()):  # what the global pipeline does after that alignment
                manager.get(i).extract_colors_for_all_images(str(image_dir), num_threads)
    return _Run([manager.get(i) for i in range(manager.size())])


def _map(database_path: Path, image_dir: Path, options: MappingOptions, num_wide: int, num_threads: int,
         on_registered: Callable[[], None] | None) -> tuple[pycolmap.Reconstruction | None, bool]:
    """The largest model of one mapper run (None when it registered nothing), and whether the mapper stopped at
    its time limit (its model is then dropped: unfinished, without its final adjustment)."""
    if options.mapper == Mapper.INCREMENTAL:
        run = _incremental(database_path, image_dir, options, num_wide, num_threads, on_registered)
    else:
        run = _global(database_path, image_dir, options, num_wide, num_threads)
    for index, model in enumerate(run.models):
        logger.info("%s model %d: %d frames, %d points%s", options.mapper, index, model.num_reg_frames(),
                    model.num_points3D(), " (time limit reached: dropped)" if run.timed_out else "")
    models = [model for model in run.models if model.num_reg_frames() > 0]
    if run.timed_out or not models:
        return None, run.timed_out
    return max(models, key=lambda rec: rec.num_reg_frames()), False


def choose_mapper(options: MappingOptions, num_wide: int) -> Mapper:
    """The mapper that runs first: the one asked for, or for ``auto`` the global mapper from
    ``options.global_from_frames`` wide frames and the incremental one below (see :class:`MappingOptions`)."""
    if options.mapper != Mapper.AUTO:
        return options.mapper
    return Mapper.GLOBAL if num_wide >= options.global_from_frames else Mapper.INCREMENTAL


@dataclass
class MappingResult:
    reconstruction: pycolmap.Reconstruction  # wide cameras registered, arbitrary units
    mapper: Mapper  # the mapper whose model was kept
    fallback: str | None = None  # why another mapper's model was kept than the one asked for


def run_mapping(
    workspace: Workspace,
    image_dir: Path,
    options: MappingOptions,
    *,
    num_wide: int,
    num_threads: int = -1,
    on_registered: Callable[[], None] | None = None,
) -> MappingResult:
    """Map the workspace's database, keep the largest model, write it to ``workspace.mapping``.

    ``auto`` runs the mapper :func:`choose_mapper` picks. If the incremental mapper cannot register every wide
    frame (e.g. neighbouring rigs share no three-view tracks) or does not finish within
    ``options.incremental_time_limit_s``, the global mapper is tried too and the model with more frames is kept;
    the result says so (``fallback``).
    """
    mapper = choose_mapper(options, num_wide)
    if mapper != options.mapper:
        logger.info("%d wide frames: the %s mapper (--mapper auto: global from %d)", num_wide, mapper,
                    options.global_from_frames)
    options = replace(options, mapper=mapper)
    kept, fallback_note = mapper, None
    best, timed_out = _map(workspace.database, image_dir, options, num_wide, num_threads, on_registered)
    if options.mapper == Mapper.INCREMENTAL and (best is None or best.num_reg_frames() < num_wide):
        registered = 0 if best is None else best.num_reg_frames()
        if timed_out:
            why = f"the incremental mapper did not finish within {options.incremental_time_limit_s:g} s"
        else:
            why = f"the incremental mapper registered {registered} of {num_wide} wide frames"
        logger.info("%s; trying the global mapper", why)
        fallback, _ = _map(workspace.database, image_dir, replace(options, mapper=Mapper.GLOBAL), num_wide,
                           num_threads, None)
        if fallback is not None and fallback.num_reg_frames() > registered:
            fallback_note = f"{why}; the global mapper's model ({fallback.num_reg_frames()} frames) is used instead"
            logger.warning("Using the global mapper's model: %s", fallback_note)
            best, kept = fallback, Mapper.GLOBAL
        elif timed_out:
            raise ReconstructionError(
                f"{why} and the global mapper registered no wide images; allow it more time "
                "(--incremental-time-limit) or check that neighbouring wide cameras overlap")
    if best is None:
        raise ReconstructionError(
            "the mapper registered no wide images: the wide views share too few verified matches. "
            "Check that neighbouring wide cameras overlap, or add manual correspondences "
            "(--manual-matches FILE; `rigsfm pick IMAGE_A IMAGE_B` helps pick them)"
        )
    with atomic_directory(workspace.mapping) as tmp:
        best.write(tmp)
    # As written: the same numbers whether this stage ran in a child process or not (reading a model back
    # normalises its rotations, a change in the 16th digit).
    return MappingResult(read_model(workspace.mapping, workspace.rerun_hint), kept, fallback_note)
