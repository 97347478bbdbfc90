"""Markdown tables and the scaling plot (OpenCV drawing; matplotlib is not a dependency) from results.json."""

from __future__ import annotations

import itertools
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from rigsfm.core.io import write_text_atomic

LABELS = {"rigsfm-incremental": "rigsfm incremental", "rigsfm-global": "rigsfm global",
          "paper": "paper (pairwise F, chained)", "colmap": "plain COLMAP", "oracle": "oracle (limit)"}
STAGES = ("features", "matching", "mapping", "adjust")
COLOURS = {"rigsfm-incremental": (180, 90, 20), "rigsfm-global": (40, 160, 40), "paper": (30, 30, 200),
           "colmap": (0, 140, 230), "oracle": (140, 60, 160)}  # BGR


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    if abs(value) >= 100:
        return f"{value:.0f}"
    return f"{value:.{digits}g}"


def _stat(runs: list[dict], key: str, stat: str):
    values = [((r.get("accuracy") or {}).get("narrow") or {}).get(key, {}) or {} for r in runs]
    values = [v.get(stat) for v in values if v.get(stat) is not None]
    if not values:
        return None
    return float(np.median(values)) if stat == "median" else float(np.max(values))


def _ratio(runs: list[dict], key: str) -> str:
    """Median over seeds of the per-seed ratio to the oracle, and the worst seed's when they differ."""
    values = [(r.get("ratio_to_oracle") or {}).get(key) for r in runs]
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    median, worst = float(np.median(values)), float(np.max(values))
    return _fmt(median) + (f" (worst {_fmt(worst)})" if worst > 1.05 * median else "")


def grouped(results: dict) -> dict[str, dict[str, list[dict]]]:
    """group label -> method -> the runs of every seed."""
    groups: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for item in results["scenarios"]:
        for method, run in item["runs"].items():
            groups[item["group"]][method].append(run)
    return groups


def _seeds(results: dict, group: str) -> str:
    return ",".join(str(s["scenario"]["seed"]) for s in results["scenarios"] if s["group"] == group)


def accuracy_table(results: dict) -> list[str]:
    lines = [("| scene (seeds) | method | narrow registered | rotation median / max (°) | direction median / max (°)"
              " | distance median / max (%) | rotation ÷ oracle | distance ÷ oracle |"),
             "|---|---|---|---|---|---|---|---|"]
    for group, methods in grouped(results).items():
        for method in results["methods"]:
            runs = methods.get(method, [])
            if not runs:
                continue
            reg = sum(((r.get("accuracy") or {}).get("narrow") or {}).get("registered", 0) for r in runs)
            total = sum(((r.get("accuracy") or {}).get("narrow") or {}).get("total", 0) for r in runs)
            cells = [f"{_fmt(_stat(runs, k, 'median'))} / {_fmt(_stat(runs, k, 'max'))}"
                     for k in ("relative_rotation_deg", "translation_direction_deg", "distance_error_percent")]
            ratios = ["" if method == "oracle" else _ratio(runs, f"{k}.median")
                      for k in ("relative_rotation_deg", "distance_error_percent")]
            label = LABELS[method] + (" ¹" if method == "colmap" else "")
            registered = f"{reg}/{total}" if total else "– (not run)"
            lines.append(f"| {group} ({_seeds(results, group)}) | {label} | {registered} | " + " | ".join(cells)
                         + " | " + " | ".join(ratios) + " |")
    return lines


def summary_table(results: dict) -> list[str]:
    """One row per scene: narrow registered, median rotation error (°), median distance error (%), time."""
    methods = list(results["methods"])
    lines = ["| scene (seeds) | " + " | ".join(LABELS[m] for m in methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for group, runs_by_method in grouped(results).items():
        cells = []
        for method in methods:
            runs = runs_by_method.get(method, [])
            reg = sum(((r.get("accuracy") or {}).get("narrow") or {}).get("registered", 0) for r in runs)
            total = sum(((r.get("accuracy") or {}).get("narrow") or {}).get("total", 0) for r in runs)
            times = [r["time_s"] for r in runs if r.get("ok") and "time_s" in r]
            if not total:
                cells.append("not run")
                continue
            cell = f"{reg}/{total}"
            if reg:
                cell += (f" · {_fmt(_stat(runs, 'relative_rotation_deg', 'median'))}°"
                         f" · {_fmt(_stat(runs, 'distance_error_percent', 'median'))} %")
            cells.append(cell + (f" · {_fmt(float(np.mean(times)))} s" if times else " · failed"))
        lines.append(f"| {group} ({_seeds(results, group)}) | " + " | ".join(cells) + " |")
    return lines


def time_table(results: dict) -> list[str]:
    methods = results["methods"]
    lines = ["| scene | " + " | ".join(LABELS[m] for m in methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for group, runs in grouped(results).items():
        cells = []
        for method in methods:
            times = [r["time_s"] for r in runs.get(method, []) if r.get("ok") and "time_s" in r]
            rss = [r["peak_rss_mb"] for r in runs.get(method, []) if "peak_rss_mb" in r]
            cells.append(f"{_fmt(np.mean(times) if times else None)} s, {_fmt(max(rss) if rss else None)} MB")
        lines.append(f"| {group} | " + " | ".join(cells) + " |")
    return lines


def stage_table(results: dict) -> list[str]:
    lines = ["| scene | mapper | " + " | ".join(STAGES) + " | other | total (s) |", "|---" * (len(STAGES) + 4) + "|"]
    for group, runs in grouped(results).items():
        for method in ("rigsfm-incremental", "rigsfm-global"):
            timings = [r["timings_s"] for r in runs.get(method, []) if r.get("ok")]
            if not timings:
                continue
            mean = {k: float(np.mean([t.get(k, 0.0) for t in timings])) for k in timings[0]}
            total = sum(mean.values())
            other = total - sum(mean.get(s, 0.0) for s in STAGES)
            cells = [f"{_fmt(mean.get(s))} ({100 * mean.get(s, 0) / total:.0f} %)" for s in STAGES]
            lines.append(f"| {group} | {method.removeprefix('rigsfm-')} | " + " | ".join(cells)
                         + f" | {_fmt(other)} | {_fmt(total)} |")
    return lines


def write_markdown(results: dict, path: Path) -> Path:
    m = results["machine"]
    head = [f"Measured {m['date']} on {m['nproc']} cores ({m['cpu']}), {m['ram_gb']} GB RAM; commit {m['commit']}"
            + (f" (uncommitted changes in {', '.join(m['uncommitted_changes_in'])})" if m['uncommitted_changes_in'] else "")
            + f"; pycolmap {m['pycolmap']}, OpenCV {m['opencv']}, Python {m['python']}; mode {results['mode']},"
            f" {results.get('total_s', 0) / 60:.0f} min in all. The machine was shared: timings are noisy"
            " (load average per run in results.json).", ""]
    text = head + ["### Summary: narrow cameras registered · median rotation error · median distance error · time", ""]
    text += summary_table(results)
    text += ["", "### Accuracy of the narrow cameras (pairwise, against the exact ground truth)", ""]
    text += accuracy_table(results)
    text += ["", "¹ no metric scale: similarity-aligned to the ground truth on its registered camera centres.",
             ("Errors: median over seeds of each seed's median, max over seeds of each seed's max. Ratios: per seed,"
              " the method's median error over the oracle's (same scene), median over seeds (worst seed)."), "",
             "### Wall time of each method and its process's peak memory (mean time over seeds, max RSS)", ""]
    text += time_table(results)
    text += ["", "### Where rigsfm's time goes (mean seconds per stage, share of the run)", ""]
    text += stage_table(results)
    return write_text_atomic(path, "\n".join(text) + "\n", overwrite=True)


def _dashed(img, p, q, colour, dash: int = 9) -> None:
    p, q = np.asarray(p, float), np.asarray(q, float)
    n = max(1, int(np.linalg.norm(q - p) / dash))
    for k in range(0, n, 2):
        a, b = p + (q - p) * k / n, p + (q - p) * min(k + 1, n) / n
        cv2.line(img, tuple(map(int, a)), tuple(map(int, b)), colour, 2, cv2.LINE_AA)


def write_scaling_plot(results: dict, path: Path, methods=("rigsfm-incremental", "rigsfm-global", "paper", "colmap")) -> Path:
    """Time (s) vs number of rigs, featureless centre: solid = image_scale 0.5, dashed = 1.0."""
    series: dict[tuple[str, float], dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for item in results["scenarios"]:
        s = item["scenario"]
        if s["textured_centre"]:
            continue
        for method in methods:
            run = item["runs"].get(method, {})
            if run.get("ok"):
                series[(method, s["image_scale"])][s["num_rigs"]].append(run["time_s"])
    width, height, left, right, top, bottom = 960, 600, 80, 250, 60, 70
    img = np.full((height, width, 3), 255, np.uint8)
    all_n = sorted({n for pts in series.values() for n in pts}) or [2, 4]
    y_max = max([np.mean(v) for pts in series.values() for v in pts.values()] or [1.0]) * 1.1
    x_lo, x_hi = 0, max(all_n) + 1
    step = 10 ** np.floor(np.log10(y_max / 4)) if y_max > 0 else 1
    step *= 2 if y_max / step > 10 else 1

    def xy(n, t):
        return (int(left + (n - x_lo) / (x_hi - x_lo) * (width - left - right)),
                int(height - bottom - t / y_max * (height - top - bottom)))

    font = cv2.FONT_HERSHEY_SIMPLEX
    for t in np.arange(0, y_max, step):
        cv2.line(img, xy(x_lo, t), xy(x_hi, t), (225, 225, 225), 1)
        cv2.putText(img, f"{t:g}", (xy(x_lo, t)[0] - 45, xy(x_lo, t)[1] + 5), font, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
    for n in all_n:
        cv2.line(img, xy(n, 0), (xy(n, 0)[0], xy(n, 0)[1] + 5), (0, 0, 0), 1)
        cv2.putText(img, str(n), (xy(n, 0)[0] - 6, xy(n, 0)[1] + 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.line(img, xy(x_lo, 0), xy(x_hi, 0), (0, 0, 0), 1)
    cv2.line(img, xy(x_lo, 0), xy(x_lo, y_max), (0, 0, 0), 1)
    cv2.putText(img, "number of rigs", (xy(x_hi / 2, 0)[0] - 60, height - 20), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "wall time (s)", (10, top - 15), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "Time vs rigs (featureless centre; solid: image_scale 0.5, dashed: 1.0)", (left, 30), font,
                0.6, (0, 0, 0), 1, cv2.LINE_AA)
    for (method, scale), pts in sorted(series.items()):
        ns = sorted(pts)
        points = [xy(n, float(np.mean(pts[n]))) for n in ns]
        colour = COLOURS[method]
        for p, q in itertools.pairwise(points):
            if scale >= 1.0:
                _dashed(img, p, q, colour)
            else:
                cv2.line(img, p, q, colour, 2, cv2.LINE_AA)
        for p in points:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
    for k, method in enumerate(methods):
        y = top + 20 + 28 * k
        cv2.line(img, (width - right + 20, y), (width - right + 50, y), COLOURS[method], 3, cv2.LINE_AA)
        cv2.putText(img, LABELS[method].split(" (")[0], (width - right + 58, y + 5), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    m = results["machine"]
    cv2.putText(img, f"{m['date'][:10]}, {m['nproc']} shared cores, commit {m['commit']}", (width - right - 150, height - 20),
                font, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path
