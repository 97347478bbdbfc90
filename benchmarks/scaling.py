"""Arena scale: rigsfm against the careful pycolmap rig recipe on full circles of 8 to 64 rigs.

    python benchmarks/scaling.py [--sizes 8 16 32 64] [--image-scale 1.0] [--scenes DIR] [--work DIR]
                                 [--methods rigsfm-incremental recipe ...] [--out benchmarks/results_scaling]
                                 [--report-only]

Scenes are rendered once (``rigsfm.synth.render_dataset``, seed 0, realistic calibration errors, featureless
centre) into ``--scenes`` and reused: a 64-rig circle at 1624x1234 takes ~10 min to render here. Every method
runs in its own process (``benchmarks/worker.py``: wall and CPU seconds, per-stage timings, peak RSS = the
process's VmHWM), one after the other; the oracle starts from the first rigsfm method's model. Writes
``OUT/results.json`` (rewritten after every run), ``OUT/results.md`` and ``OUT/scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

import benchmarks.run  # noqa: E402
from benchmarks.metrics import evaluate, ratios_to_oracle  # noqa: E402
from benchmarks.run import machine, run_child  # noqa: E402
from rigsfm.core.io import write_json_atomic, write_text_atomic  # noqa: E402
from rigsfm.synth.dataset import render_dataset  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

logger = logging.getLogger("benchmarks.scaling")

METHODS = ("rigsfm-incremental", "rigsfm-global", "recipe", "oracle")
LABELS = {"rigsfm-auto": "rigsfm (default: auto)", "rigsfm-incremental": "rigsfm (incremental)",
          "rigsfm-global": "rigsfm (global)",
          "rigsfm-exhaustive": "rigsfm, every pair matched", "recipe": "pycolmap rig recipe",
          "oracle": "oracle (limit)"}
COLOURS = {"rigsfm-auto": (20, 20, 200), "rigsfm-incremental": (180, 90, 20), "rigsfm-global": (40, 160, 40),
           "rigsfm-exhaustive": (120, 120, 120), "recipe": (0, 140, 230)}  # BGR
STAGES = ("features", "matching", "mapping", "adjust", "deliver")


def scene_dir(scenes: Path, num_rigs: int, image_scale: float) -> Path:
    return scenes / f"n{num_rigs:02d}_s{image_scale:g}"


def cached_scene(scenes: Path, num_rigs: int, image_scale: float) -> Path:
    """The rendered circle of ``num_rigs`` rigs, rendered now only if it is not there yet."""
    root = scene_dir(scenes, num_rigs, image_scale)
    if not (root / "ground_truth" / "images.bin").exists():
        start = time.perf_counter()
        render_dataset(root, SceneOptions(num_rigs=num_rigs, image_scale=image_scale, seed=0), overwrite=True)
        logger.info("rendered %s in %.0f s", root.name, time.perf_counter() - start)
    return root


def run_size(num_rigs: int, image_scale: float, scenes: Path, work: Path, methods: list[str]) -> dict:
    scene = cached_scene(scenes, num_rigs, image_scale)
    truth = pycolmap.Reconstruction(scene / "ground_truth")
    root = work / scene.name
    runs = {}
    first_rigsfm = next((m for m in methods if m.startswith("rigsfm-")), None)
    for method in methods:
        estimate = root / first_rigsfm / "model" if method == "oracle" and first_rigsfm else None
        if method == "oracle" and (estimate is None or not (estimate / "images.bin").exists()):
            runs[method] = {"ok": False, "error": "no rigsfm model to start from"}
            continue
        logger.info("%s: %s", scene.name, method)
        report = run_child(method, scene, root / method, estimate)
        model = root / method / "model"
        rec = pycolmap.Reconstruction(model) if (model / "images.bin").exists() else None
        report["accuracy"] = evaluate(rec, truth, metric=bool(report.get("metric")))
        runs[method] = report
        narrow = report["accuracy"]["narrow"]
        logger.info("  %s: %s, %.1f s (%.1f s CPU), %s MB, narrow %s/%s, rotation %s", method,
                    "ok" if report.get("ok") else report.get("error"), report.get("time_s", float("nan")),
                    report.get("cpu_s", float("nan")), report.get("peak_rss_mb"), narrow["registered"],
                    narrow["total"], (narrow.get("relative_rotation_deg") or {}).get("median"))
    oracle = (runs.get("oracle") or {}).get("accuracy", {}).get("narrow", {})
    for report in runs.values():
        if "accuracy" in report:
            report["ratio_to_oracle"] = ratios_to_oracle(report["accuracy"]["narrow"], oracle)
    return {"num_rigs": num_rigs, "image_scale": image_scale, "runs": runs}


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.{digits}g}"


def _median(report: dict, key: str):
    return (((report.get("accuracy") or {}).get("narrow") or {}).get(key) or {}).get("median")


def markdown(results: dict) -> str:
    m = results["machine"]
    lines = [f"Measured {m['date']} on {m['nproc']} cores ({m['cpu']}), commit {m['commit']}, pycolmap {m['pycolmap']}; "
             f"image scale {results['image_scale']:g}. Wall time is noisy on this shared machine (load average per "
             "run in results.json); CPU time is the process's user + system time, every thread.", "",
             "| rigs | method | wall (s) | CPU (s) | peak RSS (MB) | pairs matched / all | narrow reg. | "
             "rotation median (°) | distance median (%) | rotation ÷ oracle | distance ÷ oracle | warnings |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for size in results["sizes"]:
        for method, r in size["runs"].items():
            narrow = ((r.get("accuracy") or {}).get("narrow") or {})
            pairs = r.get("pairs") or {}
            pair_text = (f"{pairs['matched']} / {pairs['candidates']}" if pairs else
                         (f"{r['pairs_matched']} / {r['pairs_matched']}" if "pairs_matched" in r else ""))
            ratio = r.get("ratio_to_oracle") or {}
            warnings = "; ".join(w.split(":")[0] for w in r.get("warnings") or []) or ("" if r.get("ok") else
                                                                                         r.get("error", ""))
            lines.append(
                f"| {size['num_rigs']} | {LABELS.get(method, method)} | {_fmt(r.get('time_s'))} | {_fmt(r.get('cpu_s'))} | "
                f"{_fmt(r.get('peak_rss_mb'))} | {pair_text} | {narrow.get('registered', '–')}/{narrow.get('total', '–')} | "
                f"{_fmt(_median(r, 'relative_rotation_deg'))} | {_fmt(_median(r, 'distance_error_percent'))} | "
                f"{_fmt(ratio.get('relative_rotation_deg.median'))} | {_fmt(ratio.get('distance_error_percent.median'))} | "
                f"{warnings} |")
    lines += ["", "Per stage (wall s / CPU s):", "",
              "| rigs | method | " + " | ".join(STAGES) + " | other |", "|---|---|" + "---|" * (len(STAGES) + 1)]
    for size in results["sizes"]:
        for method, r in size["runs"].items():
            if method == "oracle" or not r.get("timings_s"):
                continue
            wall, cpu = r["timings_s"], r.get("stage_cpu_s") or {}
            cells = [f"{_fmt(wall.get(s))} / {_fmt(cpu.get(s))}" if s in wall else "–" for s in STAGES]
            other = sum(v for k, v in wall.items() if k not in STAGES)
            lines.append(f"| {size['num_rigs']} | {LABELS.get(method, method)} | " + " | ".join(cells) +
                         f" | {_fmt(other)} |")
    return "\n".join(lines) + "\n"


def plot(results: dict, path: Path, key: str = "time_s") -> Path:
    """Time (log) against rigs (log) per method, with N and N log N guides through rigsfm's 16-rig point."""
    width, height, margin = 900, 560, 70
    img = np.full((height, width, 3), 255, np.uint8)
    sizes = [s["num_rigs"] for s in results["sizes"]]
    series = {}
    for size in results["sizes"]:
        for method, r in size["runs"].items():
            if method != "oracle" and r.get("ok") and r.get(key):
                series.setdefault(method, []).append((size["num_rigs"], r[key]))
    values = [t for pts in series.values() for _, t in pts]
    if not values or len(sizes) < 2:
        cv2.imwrite(str(path), img)
        return path
    x0, x1 = math.log(min(sizes)), math.log(max(sizes))
    y0, y1 = math.log(min(values) / 1.5), math.log(max(values) * 1.5)

    def xy(n, t):
        return (int(margin + (math.log(n) - x0) / (x1 - x0) * (width - 2 * margin)),
                int(height - margin - (math.log(t) - y0) / (y1 - y0) * (height - 2 * margin)))

    cv2.rectangle(img, (margin, margin), (width - margin, height - margin), (0, 0, 0), 1)
    for n in sizes:
        cv2.putText(img, str(n), (xy(n, 1)[0] - 8, height - margin + 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000):
        if y0 <= math.log(t) <= y1:
            y = xy(sizes[0], t)[1]
            cv2.line(img, (margin, y), (width - margin, y), (225, 225, 225), 1)
            cv2.putText(img, f"{t} s", (10, y + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    anchor = dict(series.get("rigsfm-incremental", [])).get(16)
    if anchor:
        for label, grow in (("N log N", lambda n: n * math.log(n)), ("N^2", lambda n: n * n)):
            pts = [xy(n, anchor * grow(n) / grow(16)) for n in sizes]
            for p, q in zip(pts, pts[1:]):
                cv2.line(img, p, q, (190, 190, 190), 1, cv2.LINE_AA)
            cv2.putText(img, label, (pts[-1][0] - 60, pts[-1][1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (150, 150, 150), 1)
    for i, (method, pts) in enumerate(sorted(series.items())):
        colour = COLOURS.get(method, (0, 0, 0))
        pixels = [xy(n, t) for n, t in sorted(pts)]
        for p, q in zip(pixels, pixels[1:]):
            cv2.line(img, p, q, colour, 2, cv2.LINE_AA)
        for p in pixels:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
        cv2.putText(img, LABELS.get(method, method), (margin + 10, margin + 20 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, colour, 1, cv2.LINE_AA)
    title = ("end-to-end wall time" if key == "time_s" else "CPU time") + \
        f" vs rigs, full circles at image scale {results['image_scale']:g} (log-log)"
    cv2.putText(img, title, (margin, 40), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64])
    parser.add_argument("--image-scale", type=float, default=1.0)
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--scenes", type=Path, default=REPO / "benchmarks" / "scenes")
    parser.add_argument("--work", type=Path, default=REPO / "benchmarks" / "work_scaling")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results_scaling")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("--append", action="store_true",
                        help="add these runs to OUT/results.json (same size: methods added or replaced)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds one method may run")
    parser.add_argument("--free-initial-pair", action="store_true",
                        help="rigsfm: let COLMAP choose the initial pair (RIGSFM_BENCH_FREE_INITIAL_PAIR, see worker.py)")
    args = parser.parse_args(argv)
    if args.free_initial_pair:
        os.environ["RIGSFM_BENCH_FREE_INITIAL_PAIR"] = "1"
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    args.out.mkdir(parents=True, exist_ok=True)
    benchmarks.run.TIMEOUT_S = args.timeout
    existing = args.out / "results.json"
    if args.report_only:
        results = json.loads(existing.read_text())
    else:
        results = {"machine": machine(), "image_scale": args.image_scale, "methods": args.methods, "sizes": [],
                   "free_initial_pair": args.free_initial_pair}
        if args.append and existing.exists():
            results = json.loads(existing.read_text())
        for num_rigs in args.sizes:
            load = os.getloadavg()[0]
            size = run_size(num_rigs, args.image_scale, args.scenes, args.work, args.methods)
            for run in size["runs"].values():
                run["load_average_start"] = round(load, 2)
            same = [s for s in results["sizes"] if s["num_rigs"] == num_rigs]
            if same:
                same[0]["runs"].update(size["runs"])
                size = same[0]
            else:
                results["sizes"].append(size)
            oracle = (size["runs"].get("oracle") or {}).get("accuracy", {}).get("narrow", {})
            for run in size["runs"].values():
                if "accuracy" in run:
                    run["ratio_to_oracle"] = ratios_to_oracle(run["accuracy"]["narrow"], oracle)
            results["sizes"].sort(key=lambda s: s["num_rigs"])
            write_json_atomic(args.out / "results.json", results)
    write_text_atomic(args.out / "results.md", markdown(results))
    plot(results, args.out / "scaling.png")
    plot(results, args.out / "scaling_cpu.png", key="cpu_s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
