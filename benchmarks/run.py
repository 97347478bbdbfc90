"""Accuracy and speed of rigsfm against the paper's algorithm, plain COLMAP and the oracle, in one run.

    python benchmarks/run.py [--quick] [--out benchmarks/results] [--work DIR] [--keep] [--report-only]
                             [--rigsfm-commit REV]

For every scenario (rendered with ``rigsfm.synth.render_dataset``) each method runs in its own process
(``benchmarks/worker.py``; peak memory = that process's VmHWM, i.e. its own peak RSS), then its model is scored against the
exact ground truth. Writes ``OUT/results.json`` (every run, machine, commit; rewritten after each
scenario) and ``OUT/results.md`` (tables), and ``OUT/scaling.png`` (time vs number of rigs).
``--rigsfm-commit REV`` benchmarks the rigsfm package as committed at REV (``git archive`` into a temp
folder put first on the path) instead of the working tree, e.g. while others edit the checkout.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SNAPSHOT = os.environ.get("RIGSFM_BENCH_SNAPSHOT")  # rigsfm/ as of --rigsfm-commit, ahead of the checkout's
CODE = Path(SNAPSHOT) if SNAPSHOT else REPO
for _entry in (REPO, CODE):
    sys.path.insert(0, str(_entry))

import cv2
import pycolmap

from benchmarks.metrics import evaluate, ratios_to_oracle
from benchmarks.report import write_markdown, write_scaling_plot
from rigsfm.core.io import write_json_atomic
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions

logger = logging.getLogger("benchmarks")

METHODS = ("rigsfm-incremental", "rigsfm-global", "paper", "colmap", "oracle")
TIMEOUT_S = 900


@dataclass(frozen=True)
class Scenario:
    num_rigs: int
    arc_deg: float
    image_scale: float
    textured_centre: bool
    seed: int

    @property
    def group(self) -> str:
        centre = "crowd" if self.textured_centre else "featureless"
        arc = "circle" if self.arc_deg >= 360 else f"arc {self.arc_deg:g}"
        return f"{self.num_rigs} rigs, {arc}, {centre}, scale {self.image_scale:g}"

    @property
    def name(self) -> str:
        centre = "crowd" if self.textured_centre else "plain"
        return f"n{self.num_rigs:02d}_arc{self.arc_deg:g}_s{self.image_scale:g}_{centre}_seed{self.seed}"

    def scene_options(self) -> SceneOptions:
        return SceneOptions(num_rigs=self.num_rigs, arc_deg=self.arc_deg, image_scale=self.image_scale,
                            textured_centre=self.textured_centre, seed=self.seed)


def scenarios(quick: bool) -> list[Scenario]:
    """The quick smoke set, or the full set sized to ~40 min on 2 shared cores."""
    if quick:
        return [Scenario(2, 60, 0.5, False, 0), Scenario(4, 360, 0.5, False, 0), Scenario(2, 60, 0.5, True, 0)]
    plan = [  # (rigs, arc, image_scale, textured centre, seeds)
        (2, 60, 0.5, False, (0, 1, 2)), (4, 360, 0.5, False, (0, 1, 2)), (8, 360, 0.5, False, (0, 1)),
        (12, 360, 0.5, False, (0,)), (16, 360, 0.5, False, (0,)),
        (2, 60, 0.5, True, (0, 1)), (4, 360, 0.5, True, (0, 1)), (8, 360, 0.5, True, (0,)),
        (12, 360, 0.5, True, (0,)), (16, 360, 0.5, True, (0,)),
        (2, 60, 1.0, False, (0,)), (4, 360, 1.0, False, (0,)), (8, 360, 1.0, False, (0,)),
    ]
    return [Scenario(n, arc, s, t, seed) for n, arc, s, t, seeds in plan for seed in seeds]


def machine() -> dict:
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    mem_kb = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                  if line.startswith("MemTotal"))

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=False).stdout

    commit = os.environ.get("RIGSFM_BENCH_COMMIT") or git("rev-parse", "--short", "HEAD").strip()
    dirty_paths = ("benchmarks",) if SNAPSHOT else ("rigsfm", "benchmarks")
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "nproc": os.cpu_count(),
        "cpu": cpu,
        "ram_gb": round(mem_kb / 1024**2, 1),
        "python": platform.python_version(),
        "pycolmap": pycolmap.__version__,
        "opencv": cv2.__version__,
        "commit": commit,
        "rigsfm_code": "snapshot of the commit" if SNAPSHOT else "working tree",
        "uncommitted_changes_in": sorted({line[3:].split("/")[0]
                                          for line in git("status", "--porcelain", *dirty_paths).splitlines()}),
    }


def run_child(method: str, scene: Path, out: Path, estimate: Path | None = None) -> dict:
    """Run one method in a subprocess; its report (with its peak RSS) plus wall time and load average."""
    command = [sys.executable, "-m", "benchmarks.worker", method, str(scene), str(out)]
    if estimate is not None:
        command += ["--estimate", str(estimate)]
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys([str(CODE), str(REPO)]))}
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    with open(out / "worker.log", "w") as log:
        process = subprocess.Popen(command, cwd=CODE, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            process.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    wall = time.perf_counter() - start
    report_path = out / "worker.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {
        "ok": False, "error": f"worker died or timed out (exit {process.returncode}, {wall:.0f} s)"}
    report.pop("traceback", None)
    report.update(process_s=round(wall, 3), load_average=[round(load_before, 2), round(os.getloadavg()[0], 2)])
    return report


def run_scenario(scenario: Scenario, work: Path) -> dict:
    root = work / scenario.name
    shutil.rmtree(root, ignore_errors=True)
    start = time.perf_counter()
    dataset = render_dataset(root / "scene", scenario.scene_options())
    render_s = time.perf_counter() - start
    truth = dataset.load_ground_truth()
    runs = {}
    for method in METHODS:
        estimate = root / "rigsfm-incremental" / "model" if method == "oracle" else None
        if method == "oracle" and not (estimate / "images.bin").exists():
            runs[method] = {"ok": False, "error": "no rigsfm-incremental model to start from"}
            continue
        logger.info("%s: %s", scenario.name, method)
        report = run_child(method, dataset.root, root / method, estimate)
        model = root / method / "model"
        rec = pycolmap.Reconstruction(model) if (model / "images.bin").exists() else None
        report["accuracy"] = evaluate(rec, truth, metric=bool(report.get("metric")), align=method == "colmap")
        runs[method] = report
        narrow = report["accuracy"]["narrow"]
        logger.info("  %s: %s, %.1f s, narrow %s/%s, rot %s", method, "ok" if report["ok"] else report["error"],
                    report.get("time_s", float("nan")), narrow["registered"], narrow["total"],
                    (narrow.get("relative_rotation_deg") or {}).get("median"))
    oracle_narrow = runs["oracle"].get("accuracy", {}).get("narrow", {})
    for report in runs.values():
        if "accuracy" in report:
            report["ratio_to_oracle"] = ratios_to_oracle(report["accuracy"]["narrow"], oracle_narrow)
    return {"scenario": asdict(scenario), "group": scenario.group, "render_s": round(render_s, 3), "runs": runs}


def reexec_on_snapshot(rev: str, argv: list[str]) -> int:
    """Extract rigsfm/ at ``rev`` into a temp folder and run this script again with it first on the path."""
    commit = subprocess.run(["git", "rev-parse", "--short", rev], cwd=REPO, capture_output=True, text=True,
                            check=True).stdout.strip()
    snapshot = Path(tempfile.mkdtemp(prefix="rigsfm-bench-code-"))
    archive = subprocess.run(["git", "archive", commit, "rigsfm"], cwd=REPO, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(snapshot)], input=archive.stdout, check=True)
    rest, skip = [], False
    for arg in argv:
        if skip or arg.startswith("--rigsfm-commit"):
            skip = arg == "--rigsfm-commit"
            continue
        rest.append(arg)
    env = {**os.environ, "RIGSFM_BENCH_SNAPSHOT": str(snapshot), "RIGSFM_BENCH_COMMIT": commit}
    try:
        return subprocess.run([sys.executable, str(Path(__file__).resolve()), *rest], env=env, check=False).returncode
    finally:
        shutil.rmtree(snapshot, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="rigsfm benchmarks: accuracy and speed vs the alternatives")
    parser.add_argument("--quick", action="store_true", help="2 and 4 rigs, image_scale 0.5, one seed")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument("--work", type=Path, help="scratch folder for scenes and runs (default: a temp dir)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder")
    parser.add_argument("--report-only", action="store_true", help="only redraw results.md and scaling.png")
    parser.add_argument("--rigsfm-commit", metavar="REV", help="benchmark rigsfm/ as committed at REV")
    args = parser.parse_args(argv)
    if args.rigsfm_commit:
        return reexec_on_snapshot(args.rigsfm_commit, argv if argv is not None else sys.argv[1:])
    if args.report_only:
        results = json.loads((args.out / "results.json").read_text())
        write_markdown(results, args.out / "results.md")
        write_scaling_plot(results, args.out / "scaling.png")
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("rigsfm").setLevel(logging.WARNING)
    work = args.work or Path(tempfile.mkdtemp(prefix="rigsfm-bench-"))
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"mode": "quick" if args.quick else "full", "machine": machine(), "methods": list(METHODS),
               "scenarios": []}
    results["idle"] = run_child("idle", work, work / "idle")
    start = time.perf_counter()
    try:
        for scenario in scenarios(args.quick):
            results["scenarios"].append(run_scenario(scenario, work))
            results["total_s"] = round(time.perf_counter() - start, 1)
            write_json_atomic(args.out / "results.json", results)
            if not args.keep:
                shutil.rmtree(work / scenario.name, ignore_errors=True)
    finally:
        if not args.keep and args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    results["machine"]["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    write_json_atomic(args.out / "results.json", results)
    write_markdown(results, args.out / "results.md")
    write_scaling_plot(results, args.out / "scaling.png")
    logger.info("done in %.0f s: %s", time.perf_counter() - start, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
