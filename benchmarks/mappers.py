"""The mappers on one matched database: rigsfm's global and incremental settings against COLMAP's hierarchical mapper.

    python benchmarks/mappers.py SCENE WORKSPACE [--methods global incremental hierarchical-16x2 flat-2x2 ...]
                                 [--out DIR] [--again]

``SCENE``: a rendered scene (``images/``, ``rigs.yaml``, ``scale.yaml``, ``ground_truth/``), e.g.
``benchmarks/scenes/n64_s1``; ``WORKSPACE``: a finished ``rigsfm run`` of it (its ``database.db``: features and
verified matches as rigsfm made them). Every mapper runs in its own process on a copy of that database
(wall and CPU seconds of the mapping alone, the process's peak RSS); its model then goes through rigsfm's own
adjustment (calibration refined with its priors, metric scale; no covariance) and is scored against the truth.
Each method's report is kept in ``OUT/METHOD/report.json`` (a method already there is not run again without
``--again``); the table lists every report in OUT.

``hierarchical-LxW``: ``pycolmap.HierarchicalPipeline`` (COLMAP's hierarchical mapper) with its default recursive
clustering into leaves of at most L images, the incremental mapper on each leaf with rigsfm's incremental settings
(intrinsics and ``sensor_from_rig`` fixed, two-view tracks kept), W leaves at a time, the leaves' models merged.
``flat-PxW``: the same with one flat cut into P parts (``clustering_options.is_hierarchical = False``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

logger = logging.getLogger("benchmarks.mappers")


def map_one(method: str, database: Path, image_dir: Path, num_wide: int, out: Path) -> dict:
    """Run one mapper on ``database``; write its largest model to ``out``; its timings."""
    import pycolmap

    from rigsfm.run.mapping.mapper import _incremental_options, _map
    from rigsfm.run.options import Mapper, MappingOptions

    threads = os.cpu_count() or 1
    options = MappingOptions()
    start, cpu_start = time.perf_counter(), time.process_time()
    if method in ("global", "incremental"):
        model, _ = _map(database, image_dir, MappingOptions(mapper=Mapper(method)), num_wide, -1, None)
        models = [] if model is None else [model]
    else:
        kind, sizes = method.split("-")
        size, workers = (int(part) for part in sizes.split("x"))
        pipeline = pycolmap.HierarchicalPipelineOptions()
        pipeline.image_path = str(image_dir)
        pipeline.num_workers = workers
        pipeline.num_threads = threads
        if kind == "flat":
            pipeline.clustering_options.is_hierarchical = False
            pipeline.clustering_options.branching = size
        else:
            pipeline.clustering_options.leaf_max_num_images = size
        incremental = _incremental_options(options, num_wide, -1)
        incremental.multiple_models = True  # a leaf's images may split; the merge joins what overlaps
        incremental.min_model_size = min(incremental.min_model_size, 3)
        pipeline.incremental_options = incremental
        manager = pycolmap.ReconstructionManager()
        with pycolmap.Database.open(database) as db:
            pycolmap.HierarchicalPipeline(pipeline, db, manager).run()
        models = [manager.get(i) for i in range(manager.size())]
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    sizes = sorted((m.num_reg_frames() for m in models), reverse=True)
    best = max(models, key=lambda m: m.num_reg_frames()) if models else None
    if best is not None:
        out.mkdir(parents=True, exist_ok=True)
        best.write(out)
    return {"method": method, "mapping_s": round(wall, 2), "mapping_cpu_s": round(cpu, 2), "models": sizes,
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "points": 0 if best is None else best.num_points3D()}


def adjust_and_score(scene: Path, model: Path) -> dict:
    import pycolmap

    from benchmarks.metrics import evaluate
    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.pipeline import load_inputs

    inputs = load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml")
    truth = pycolmap.Reconstruction(scene / "ground_truth")
    start = time.perf_counter()
    result = adjust(pycolmap.Reconstruction(model), inputs.rigs, inputs.scale, priors=inputs.priors,
                    with_covariance=False)
    scores = evaluate(result.reconstruction, truth, metric=True)["narrow"]
    return {"adjust_s": round(time.perf_counter() - start, 1), "narrow": scores}


def child(method: str, scene: Path, workspace: Path, out: Path) -> None:
    """One mapper in this process (so that its peak RSS is its own), on a private copy of the database."""
    from rigsfm.core.names import ImageName
    from rigsfm.run.inputs.database import open_database

    with tempfile.TemporaryDirectory() as tmp:
        database = Path(tmp) / "database.db"
        shutil.copy(workspace / "database.db", database)
        with open_database(database) as db:
            num_wide = sum(ImageName.parse(image.name).sensor == "wide" for image in db.read_all_images())
        try:
            report = map_one(method, database, scene / "images", num_wide, out / "model")
        except Exception as error:  # noqa: BLE001  (a mapper's failure is a benchmark result)
            report = {"method": method, "error": f"{type(error).__name__}: {error}", "models": []}
    report["num_wide"] = num_wide
    if report["models"]:
        report.update(adjust_and_score(scene, out / "model"))
    (out / "report.json").write_text(json.dumps(report, indent=1, default=float))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--methods", nargs="+", default=["global", "incremental", "hierarchical-16x2", "flat-2x2"])
    parser.add_argument("--again", action="store_true", help="run methods whose report is already in OUT again")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "rigsfm_mappers")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if args.child:
        child(args.child, args.scene, args.workspace, args.out / args.child)
        return 0
    for method in args.methods:
        out = args.out / method
        if (out / "report.json").exists() and not args.again:
            continue
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        start = time.perf_counter()
        with open(out / "colmap.log", "w") as log:
            subprocess.run([sys.executable, __file__, str(args.scene), str(args.workspace), "--out", str(args.out),
                            "--child", method], stdout=log, stderr=subprocess.STDOUT, check=False)
        report_path = out / "report.json"
        report = json.loads(report_path.read_text()) if report_path.exists() else {
            "method": method, "error": "the mapper's process died (see colmap.log)", "models": []}
        report["process_s"] = round(time.perf_counter() - start, 1)
        report_path.write_text(json.dumps(report, indent=1, default=float))
        logger.warning("%s: %s", method, {k: v for k, v in report.items() if k != "narrow"})
    results = [json.loads(path.read_text()) for path in sorted(args.out.glob("*/report.json"))]
    (args.out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    print("| mapper | mapping (s) | mapping CPU (s) | peak RSS (MB) | models (frames) | points | narrow reg. "
          "| rotation median / max (°) | distance median / max (%) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        if r.get("error"):
            print(f"| {r['method']} | failed after {r.get('process_s')} s: {r['error']} |")
            continue
        n = r.get("narrow") or {}
        rot, dist = n.get("relative_rotation_deg") or {}, n.get("distance_error_percent") or {}
        print(f"| {r['method']} | {r.get('mapping_s')} | {r.get('mapping_cpu_s')} | {r.get('peak_rss_mb')} "
              f"| {r.get('models')} | {r.get('points')} | {n.get('registered')}/{n.get('total')} "
              f"| {rot.get('median', float('nan')):.4f} / {rot.get('max', float('nan')):.4f} "
              f"| {dist.get('median', float('nan')):.4f} / {dist.get('max', float('nan')):.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
