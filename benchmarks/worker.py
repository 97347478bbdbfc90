"""One method on one rendered scene, in its own process (so the parent can read its peak RSS).

``python -m benchmarks.worker METHOD SCENE OUT [--estimate MODEL]`` writes ``OUT/model`` (a COLMAP
model, if the method produced one) and ``OUT/worker.json`` (time of the method itself, after the common
imports; per-stage timings; the process's peak RSS; method-specific facts). METHOD: rigsfm-auto (the default),
rigsfm-incremental, rigsfm-global, rigsfm-exhaustive (incremental, every pair matched), paper, colmap,
recipe (the careful pycolmap rig recipe, baselines/colmap_recipe.py), oracle (needs --estimate: the rigsfm
model whose observations it re-uses), idle (imports only: the floor of the peak memory).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import time
import traceback
from pathlib import Path

METHODS = ("rigsfm-auto", "rigsfm-incremental", "rigsfm-global", "rigsfm-exhaustive", "paper", "colmap", "recipe",
           "oracle", "idle")


def import_common() -> None:
    """Heavy imports shared by every method, done before the clock starts (and all that ``idle`` does)."""
    import cv2  # noqa: F401
    import pycolmap  # noqa: F401
    import scipy.optimize  # noqa: F401



def peak_rss_mb() -> float:
    """The run's peak resident memory (MB, VmHWM, C++ allocations included): this process's or that of any of
    rigsfm's stage processes, whichever is larger (``rigsfm.core.processes.stage_peak_rss_mb``).

    Not ``ru_maxrss`` from the parent's ``wait4``: Linux carries the parent's peak RSS at fork over
    the exec into the child's ru_maxrss, so every child would report at least the parent's size.
    """
    from rigsfm.core.processes import stage_peak_rss_mb

    return round(stage_peak_rss_mb(), 1)


def cpu_seconds() -> float:
    """User + system CPU time of this process and of rigsfm's stage processes (which the forkserver, not this
    process, waits for), every thread included (robust to a shared machine's load)."""
    from rigsfm.core.processes import stage_cpu_seconds

    return stage_cpu_seconds()


def run_method(method: str, scene: Path, out: Path, estimate: Path | None) -> dict:
    import pycolmap

    if method == "idle":
        return {"timings_s": {}, "metric": False}
    if method.startswith("rigsfm-"):
        if os.environ.get("RIGSFM_BENCH_FREE_INITIAL_PAIR"):
            # Let COLMAP choose the initial pair (what the fix of rigsfm.run.mapping.mapper.initial_pair, under way in
            # parallel, does when the strongest pair is too narrow to start from): the forced pair of a full
            # circle is rejected and retried 1000 times (~160 s at 16 rigs).
            import rigsfm.run.mapping.mapper

            rigsfm.run.mapping.mapper.initial_pair = lambda database_path: None
        from rigsfm.run.options import Mapper, MappingOptions, MatchingOptions, Pairs
        from rigsfm.run.pipeline import RunOptions, run

        if method == "rigsfm-exhaustive":
            options = RunOptions(matching=MatchingOptions(pairs=Pairs.EXHAUSTIVE))
        else:
            options = RunOptions(mapping=MappingOptions(mapper=Mapper(method.removeprefix("rigsfm-"))))
        result = run(scene / "images", scene / "rigs.yaml", out / "run", scene / "scale.yaml", options)
        shutil.copytree(out / "run" / "sparse", out / "model")
        return {"timings_s": result.summary.timings_s, "stage_cpu_s": getattr(result.summary, "cpu_s", {}),
                "metric": result.summary.metric,
                "scale": result.summary.scale.source, "warnings": result.summary.warnings,
                "pairs": getattr(result.summary, "pairs", None), "mapper_used": result.summary.mapping.used}
    if method == "paper":
        from benchmarks.baselines.paper import run_paper

        rec, report = run_paper(scene)
        (out / "model").mkdir()
        rec.write(out / "model")
        return report
    if method == "colmap":
        from benchmarks.baselines.plain_colmap import run_plain_colmap

        rec, report = run_plain_colmap(scene / "images", out / "work")
        if rec is not None:
            (out / "model").mkdir()
            rec.write(out / "model")
        return {**report, "metric": False}
    if method == "recipe":
        from benchmarks.baselines.colmap_recipe import run_colmap_recipe

        rec, report = run_colmap_recipe(scene, out / "work")
        if rec is not None:
            (out / "model").mkdir()
            rec.write(out / "model")
        shutil.rmtree(out / "work", ignore_errors=True)
        return {**report, "metric": rec is not None}
    if method == "oracle":
        from rigsfm.run.pipeline import load_inputs
        from rigsfm.synth.truth import oracle

        if estimate is None:
            raise ValueError("oracle needs --estimate")
        inputs = load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml")
        truth = pycolmap.Reconstruction(scene / "ground_truth")
        start = time.perf_counter()
        rec = oracle(pycolmap.Reconstruction(estimate), truth, inputs.rigs, inputs.scale)
        (out / "model").mkdir()
        rec.write(out / "model")
        return {"timings_s": {"oracle": round(time.perf_counter() - start, 3)}, "metric": True}
    raise ValueError(f"unknown method {method!r}; use one of {', '.join(METHODS)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method", choices=METHODS)
    parser.add_argument("scene", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--estimate", type=Path)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(args.out / "model", ignore_errors=True)
    import_common()
    start, cpu_start = time.perf_counter(), cpu_seconds()
    try:
        report = run_method(args.method, args.scene, args.out, args.estimate)
        report.update(ok=True, error=None)
    except Exception as error:  # noqa: BLE001  (recorded, not raised: a failure is a benchmark result)
        report = {"ok": False, "error": f"{type(error).__name__}: {error}", "traceback": traceback.format_exc()}
    report["method"] = args.method
    report["time_s"] = round(time.perf_counter() - start, 3)
    report["cpu_s"] = round(cpu_seconds() - cpu_start, 3)
    report["peak_rss_mb"] = peak_rss_mb()
    (args.out / "worker.json").write_text(json.dumps(report, indent=1, default=str))
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
