"""Stage 3: register the wide cameras with COLMAP's incremental or global mapper.

Intrinsics and every ``sensor_from_rig`` (E^sl) stay fixed. Small networks (2-4 rigs) only have
two-view tracks, which COLMAP ignores by default; they are allowed here, and the model-size and
track-length minimums are lowered to what the network can provide.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.names import ImageName, Sensor
from rigsfm.core.errors import ReconstructionError
from rigsfm.core.io import atomic_directory
from rigsfm.core.workspace import Workspace
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
    # Rigs far apart round an arena share many points between neighbours only: keep two-view tracks
    # (verified, and the rig-constraint stage adjusts with a robust loss and drops outliers). Measured at 12 and
    # 16 rigs: they cost 1.5-1.7x the mapping CPU and 1.4-2.2x the adjustment's, and they pay where the wide
    # views share a textured centre (12-rig crowd circle: narrow distance error 0.24 % with, 0.37 % without;
    # rotation 0.140 vs 0.147 deg); on a featureless centre they change nothing (16 rigs: 0.316 vs 0.320 %).
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
    return pipeline


FEW_MATCHES_MIN_INLIERS = 8  # the least a pair of manual correspondences keeps (rigsfm.run.manual_matches)


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


def best_pair_inliers(database_path: Path) -> int:
    """Verified inliers of the best wide-wide pair of two different rigs (0 if none)."""
    pair = initial_pair(database_path)
    if pair is None:
        return 0
    with pycolmap.Database.open(database_path) as database:
        return len(database.read_two_view_geometry(*pair).inlier_matches)


def initial_pair(database_path: Path) -> tuple[int, int] | None:
    """The wide-wide pair of two different rigs with the most verified inliers.

    Choosing it up front spares the mapper's initial-pair search, which can run for minutes when the
    narrow images carry many (e.g. moving-crowd) features.
    """
    with pycolmap.Database.open(database_path) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    best, best_inliers = None, 0
    for pair_id, count in zip(pair_ids, inliers):
        id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
        one, two = ImageName.parse(names[id1]), ImageName.parse(names[id2])
        if one.sensor == two.sensor == Sensor.WIDE and one.rig != two.rig and count > best_inliers:
            best, best_inliers = (id1, id2), count
    return best


def mapping_database(database_path: Path, path: Path, *, keep_narrow_offsets: bool) -> Path:
    """The database the mapper reads: a copy of ``database_path``, narrow offsets zeroed by default.

    Works around pycolmap 4.2.1: after mapping, ``AlignReconstructionToOrigRigScales`` looks
    up every rig whose non-reference sensor has a non-zero ``sensor_from_rig`` translation and raises
    ``IndexError: Rig with ID n does not exist`` for a rig none of whose frames registered. Without
    narrow features the narrow images carry no observations, so their offset plays no part in mapping;
    zeroing it (rotation kept) avoids the crash, and the rig-constraint stage restores E^sl.
    """
    tmp = path.with_name(path.name + ".tmp")
    shutil.copyfile(database_path, tmp)
    if not keep_narrow_offsets:
        with pycolmap.Database.open(tmp) as database:
            for rig in database.read_all_rigs():
                for sensor_id, sensor_from_rig in rig.non_ref_sensors.items():
                    if sensor_from_rig is not None:
                        rig.set_sensor_from_rig(sensor_id, pycolmap.Rigid3d(sensor_from_rig.rotation, np.zeros(3)))
                database.update_rig(rig)
    tmp.replace(path)
    return path


def _incremental(database_path: Path, image_dir: Path, models_dir: Path, options: MappingOptions, num_wide: int,
                 num_threads: int, on_registered: Callable[[], None] | None) -> dict[int, pycolmap.Reconstruction]:
    pipeline = _incremental_options(options, num_wide, num_threads)
    if options.few_matches:
        relax_for_few_matches(pipeline, best_pair_inliers(database_path))
    pair = initial_pair(database_path)
    if pair is not None:
        pipeline.init_image_id1, pipeline.init_image_id2 = pair
    models = pycolmap.incremental_mapping(
        database_path, image_dir, models_dir, pipeline, next_image_callback=on_registered
    )
    if not models and pair is not None:
        logger.warning("Mapping from the initial pair %s failed; searching for another", pair)
        pipeline.init_image_id1 = pipeline.init_image_id2 = -1
        models = pycolmap.incremental_mapping(
            database_path, image_dir, models_dir, pipeline, next_image_callback=on_registered
        )
    return models


def _map(database_path: Path, image_dir: Path, models_dir: Path, options: MappingOptions, num_wide: int,
         num_threads: int, on_registered: Callable[[], None] | None) -> pycolmap.Reconstruction | None:
    """The largest model of one mapper run, or None when it registered nothing."""
    shutil.rmtree(models_dir, ignore_errors=True)
    models_dir.mkdir()
    if options.mapper == Mapper.INCREMENTAL:
        models = _incremental(database_path, image_dir, models_dir, options, num_wide, num_threads, on_registered)
    else:
        models = pycolmap.global_mapping(database_path, image_dir, models_dir,
                                         _global_options(options, num_wide, num_threads))
    for index, model in models.items():
        logger.info("%s model %d: %d frames, %d points", options.mapper, index, model.num_reg_frames(),
                    model.num_points3D())
    shutil.rmtree(models_dir)
    return max(models.values(), key=lambda rec: rec.num_reg_frames()) if models else None


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
    keep_narrow_offsets: bool = False,
    num_threads: int = -1,
    on_registered: Callable[[], None] | None = None,
) -> MappingResult:
    """Map the workspace's database, keep the largest model, write it to ``workspace.mapping``.

    If the incremental mapper cannot register every wide frame (e.g. neighbouring rigs share no
    three-view tracks), the global mapper is tried too and the model with more frames is kept; the
    result says so (``fallback``).
    """
    mapping_db = workspace.mapping_database
    fallback_note = None
    kept = options.mapper
    with atomic_directory(workspace.mapping) as tmp:
        models_dir = tmp / "models"
        mapping_database(workspace.database, mapping_db, keep_narrow_offsets=keep_narrow_offsets)
        try:
            best = _map(mapping_db, image_dir, models_dir, options, num_wide, num_threads, on_registered)
        except IndexError as error:  # pycolmap 4.2.1 rig-scale alignment bug, see mapping_database
            if not keep_narrow_offsets:
                raise
            logger.warning("COLMAP failed with narrow offsets (%s); mapping the wide cameras alone", error)
            mapping_database(workspace.database, mapping_db, keep_narrow_offsets=False)
            best = _map(mapping_db, image_dir, models_dir, options, num_wide, num_threads, on_registered)
        if options.mapper == Mapper.INCREMENTAL and (best is None or best.num_reg_frames() < num_wide):
            registered = 0 if best is None else best.num_reg_frames()
            logger.info("The incremental mapper registered %d of %d frames; trying the global mapper",
                        registered, num_wide)
            fallback = _map(mapping_db, image_dir, models_dir, replace(options, mapper=Mapper.GLOBAL), num_wide,
                            num_threads, None)
            if fallback is not None and fallback.num_reg_frames() > registered:
                fallback_note = (f"the incremental mapper registered {registered} of {num_wide} wide frames; the "
                                 f"global mapper's model ({fallback.num_reg_frames()} frames) is used instead")
                logger.warning("Using the global mapper's model: %s", fallback_note)
                best, kept = fallback, Mapper.GLOBAL
        if best is None:
            raise ReconstructionError(
                "the mapper registered no wide images: the wide views share too few verified matches. "
                "Check that neighbouring wide cameras overlap, or add manual correspondences "
                "(--manual-matches FILE; `rigsfm pick IMAGE_A IMAGE_B` helps pick them)"
            )
        best.write(tmp)
    return MappingResult(pycolmap.Reconstruction(workspace.mapping), kept, fallback_note)
