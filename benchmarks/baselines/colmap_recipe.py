"""The careful pycolmap rig recipe, as a baseline: what a COLMAP-savvy user writes by hand in ~30 lines.

1. Rig config: the calibrated cameras of rigs.yaml (never refined) and one ``pycolmap.Rig`` per rig with
   ``narrow_from_wide`` as the narrow sensor's ``sensor_from_rig`` (``pycolmap.apply_rig_config``; the same
   database rigsfm's stage 1 writes, so both start from the same rig configuration).
2. All images, wide and narrow: ``pycolmap.extract_features`` (default SIFT options, 8192 features).
3. Exhaustive matching: ``pycolmap.match_exhaustive`` with default options (ratio 0.8, cross-check, COLMAP's
   default two-view verification).
4. The incremental mapper with the calibration held: intrinsics and ``sensor_from_rig`` not refined;
   otherwise COLMAP's defaults (two-view tracks ignored, COLMAP picks the initial pair). The largest model.
5. Metric fix: the similarity scale from scale.yaml (``rigsfm.run.adjustment.scale.estimate_scale``: the rangefinder
   distance and the known length), then E^sl and the intrinsics restored from rigs.yaml (a Sim3 scales every
   ``sensor_from_rig`` too). No further adjustment.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.run.adjustment.adjust import restore_calibration
from rigsfm.run.adjustment.scale import estimate_scale
from rigsfm.run.inputs.database import create_database
from rigsfm.run.pipeline import load_inputs


def run_colmap_recipe(scene: Path, out: Path, num_threads: int = -1) -> tuple[pycolmap.Reconstruction | None, dict]:
    """Run the recipe on a rendered scene folder (images/, rigs.yaml, scale.yaml) in ``out``."""
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    database, models_dir = out / "database.db", out / "models"
    models_dir.mkdir()
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    clock = [time.process_time()]  # this process's CPU time, every thread

    def timed(stage: str, start: float) -> float:
        timings[stage] = round(time.perf_counter() - start, 3)
        cpu[stage] = round(time.process_time() - clock[0], 3)
        clock[0] = time.process_time()
        return time.perf_counter()

    start = time.perf_counter()
    inputs = load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml")
    create_database(database, inputs.rigs, inputs.images)
    start = timed("database", start)
    extraction = pycolmap.FeatureExtractionOptions(num_threads=num_threads, use_gpu=False)
    pycolmap.extract_features(database, inputs.image_dir, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              extraction_options=extraction)
    start = timed("features", start)
    pycolmap.match_exhaustive(database, matching_options=pycolmap.FeatureMatchingOptions(num_threads=num_threads,
                                                                                          use_gpu=False))
    start = timed("matching", start)
    pipeline = pycolmap.IncrementalPipelineOptions(
        num_threads=num_threads, ba_refine_focal_length=False, ba_refine_principal_point=False,
        ba_refine_extra_params=False, ba_refine_sensor_from_rig=False)
    models = pycolmap.incremental_mapping(database, inputs.image_dir, models_dir, pipeline)
    start = timed("mapping", start)
    report = {"num_models": len(models),
              "model_sizes": sorted((m.num_reg_frames() for m in models.values()), reverse=True)}
    with pycolmap.Database.open(database) as db:
        report["pairs_matched"] = db.num_matched_image_pairs()
        report["pairs_verified"] = db.num_verified_image_pairs()
    if not models:
        report.update(timings_s=timings, stage_cpu_s=cpu)
        return None, report
    rec = max(models.values(), key=lambda m: m.num_reg_frames())
    scale = estimate_scale(rec, inputs.scale)
    rec.transform(pycolmap.Sim3d(scale.metres_per_unit, pycolmap.Rotation3d(), np.zeros(3)))
    restore_calibration(rec, inputs.rigs)
    timed("metric_fix", start)
    report.update(timings_s=timings, stage_cpu_s=cpu, metres_per_unit=scale.metres_per_unit)
    return rec, report
