"""Plain COLMAP, as a baseline: what a user gets by pointing pycolmap at the image folder.

Every image (wide and narrow), no rig configuration, no calibration file, default options throughout:
``extract_features`` (camera model and focal length guessed, CameraMode.AUTO), ``match_exhaustive``,
``incremental_mapping``. The largest model is kept. It has no metric scale; the evaluation aligns it to
the ground truth with a similarity on its registered camera centres (which favours this baseline).
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

logger = logging.getLogger(__name__)


def run_plain_colmap(image_dir: Path, out: Path) -> tuple[pycolmap.Reconstruction | None, dict]:
    """Run the three default stages in ``out``; returns the largest model (None if none) and a report."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    database = out / "database.db"
    database.unlink(missing_ok=True)
    models_dir = out / "models"
    shutil.rmtree(models_dir, ignore_errors=True)
    models_dir.mkdir()
    timings = {}
    start = time.perf_counter()
    pycolmap.extract_features(database, image_dir)
    timings["features"] = time.perf_counter() - start
    start = time.perf_counter()
    pycolmap.match_exhaustive(database)
    timings["matching"] = time.perf_counter() - start
    start = time.perf_counter()
    models = pycolmap.incremental_mapping(database, image_dir, models_dir)
    timings["mapping"] = time.perf_counter() - start
    with pycolmap.Database.open(database) as db:
        num_cameras = len(db.read_all_cameras())
        keypoints = {image.name: db.read_keypoints(image.image_id).shape[0] for image in db.read_all_images()}
    report = {
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "num_models": len(models),
        "model_sizes": sorted((m.num_reg_images() for m in models.values()), reverse=True),
        "num_cameras_created": num_cameras,
        "mean_keypoints": {
            sensor: float(np.mean([n for name, n in keypoints.items() if f"/{sensor}/" in name] or [0]))
            for sensor in ("wide", "narrow")
        },
    }
    if not models:
        return None, report
    return max(models.values(), key=lambda rec: rec.num_reg_images()), report
