"""Stage 3: register the wide cameras with COLMAP's incremental or global mapper.

Intrinsics and every ``sensor_from_rig`` (E^sl) stay fixed. Small networks (2-4 rigs) only have
two-view tracks, which COLMAP ignores by default; they are allowed here, and the model-size and
track-length minimums are lowered to what the network can provide.
"""

from __future__ import annotations

import enum
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from rigsfm.errors import ReconstructionError
from rigsfm.io import atomic_directory

logger = logging.getLogger(__name__)


class Mapper(enum.StrEnum):
    INCREMENTAL = "incremental"
    GLOBAL = "global"


@dataclass(kw_only=True)
class MappingOptions:
    mapper: Mapper = Mapper.INCREMENTAL
    seed: int = 0
    num_threads: int = -1


def _incremental_options(options: MappingOptions, num_wide: int) -> pycolmap.IncrementalPipelineOptions:
    pipeline = pycolmap.IncrementalPipelineOptions(
        num_threads=options.num_threads,
        random_seed=options.seed,
        ba_refine_focal_length=False,
        ba_refine_principal_point=False,
        ba_refine_extra_params=False,
        ba_refine_sensor_from_rig=False,
        min_model_size=min(10, max(2, num_wide)),
        extract_colors=True,
    )
    pipeline.mapper.abs_pose_refine_focal_length = False
    pipeline.mapper.abs_pose_refine_extra_params = False
    if num_wide <= 4:
        pipeline.triangulation.ignore_two_view_tracks = False
    return pipeline


def _global_options(options: MappingOptions, num_wide: int) -> pycolmap.GlobalPipelineOptions:
    pipeline = pycolmap.GlobalPipelineOptions(
        num_threads=options.num_threads, random_seed=options.seed, min_model_size=min(3, max(2, num_wide))
    )
    mapper = pipeline.mapper
    mapper.num_threads = options.num_threads
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
    if num_wide <= 4:
        mapper.track_min_num_views_per_track = 2
        mapper.global_positioning.min_num_view_per_track = 2
        mapper.bundle_adjustment.min_track_length = 2
        mapper.retriangulation.ignore_two_view_tracks = False
    return pipeline


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
        rig1, sensor1, _ = names[id1].split("/", 2)
        rig2, sensor2, _ = names[id2].split("/", 2)
        if sensor1 == sensor2 == "wide" and rig1 != rig2 and count > best_inliers:
            best, best_inliers = (id1, id2), count
    return best


def run_mapping(
    database_path: Path,
    image_dir: Path,
    output_path: Path,
    options: MappingOptions,
    num_wide: int,
    on_registered: Callable[[], None] | None = None,
) -> pycolmap.Reconstruction:
    """Map, keep the largest model, write it to ``output_path`` (atomically) and return it."""
    with atomic_directory(output_path) as tmp:
        models_dir = tmp / "models"
        models_dir.mkdir()
        if options.mapper == Mapper.INCREMENTAL:
            pipeline = _incremental_options(options, num_wide)
            pair = initial_pair(database_path)
            if pair is not None:
                pipeline.init_image_id1, pipeline.init_image_id2 = pair
            models = pycolmap.incremental_mapping(
                database_path, image_dir, models_dir, pipeline, next_image_callback=on_registered
            )
            if not models and pair is not None:
                logger.warning("Mapping from the initial pair %s failed; searching for another", pair)
                shutil.rmtree(models_dir)
                models_dir.mkdir()
                pipeline.init_image_id1 = pipeline.init_image_id2 = -1
                models = pycolmap.incremental_mapping(
                    database_path, image_dir, models_dir, pipeline, next_image_callback=on_registered
                )
        else:
            models = pycolmap.global_mapping(
                database_path, image_dir, models_dir, _global_options(options, num_wide)
            )
        if not models:
            raise ReconstructionError(
                "the mapper registered no wide images: the wide views share too few verified matches. "
                "Check that neighbouring wide cameras overlap, or add manual correspondences"
            )
        best = max(models.values(), key=lambda rec: rec.num_reg_frames())
        for index, model in models.items():
            logger.info("Model %d: %s", index, model.summary().replace("\n", " "))
        shutil.rmtree(models_dir)
        best.write(tmp)
    return pycolmap.Reconstruction(output_path)
