"""How far apart can two rigs be? SIFT, ASIFT and simulated manual clicks against angular separation.

    python benchmarks/separation.py [--arcs 60 90 120 140 150 160 170] [--clicks 34 60 100] [--click-sets 10]
                                    [--asift] [--out benchmarks/results] [--work DIR]

Two rigs on the synthetic arena (wide-angle 500 px lenses, 1624x1234, realistic calibration errors),
``arc`` degrees apart seen from the arena centre. Per separation: ``rigsfm run`` with SIFT (and ASIFT with
``--asift``), then with N simulated clicks (``rigsfm.synth.clicks``: spread over the stands, pillars, boxes
and ground both views show, 1 px noise per coordinate, 20 % gross outliers) for several click sets. Scores:
narrow relative-rotation error against the exact ground truth, the warnings, and the failure messages.
Writes ``OUT/separation.json`` and ``OUT/separation.md``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rigsfm.core.errors import RigsfmError
from rigsfm.core.io import write_json_atomic, write_text_atomic
from rigsfm.run.matching.manual_matches import write_manual_matches
from rigsfm.run.options import Features, MatchingOptions
from rigsfm.run.pipeline import RunOptions, run
from rigsfm.synth.clicks import simulate_clicks
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions, build_arena
from rigsfm.synth.truth import compare_to_ground_truth

A, B = "rig01/wide/frame0000.png", "rig02/wide/frame0000.png"
WIDE_FOCAL = 500.0


def attempt(dataset, out: Path, options: RunOptions) -> dict:
    """One run: its narrow error, warnings, and time; or its failure message."""
    start = time.perf_counter()
    try:
        result = run(dataset.images, dataset.rigs, out, dataset.scale, options)
    except RigsfmError as error:
        return {"ok": False, "error": str(error), "seconds": round(time.perf_counter() - start, 1)}
    scores = compare_to_ground_truth(result.reconstruction, dataset.load_ground_truth())
    return {"ok": True, "narrow_rotation_error_deg": scores["relative_rotation_deg"]["max"],
            "registered_narrow": scores.get("registered", None), "warnings": result.summary.warnings,
            "seconds": round(time.perf_counter() - start, 1)}


def separation(arc: float, work: Path, clicks: list[int], click_sets: int, asift: bool) -> dict:
    options = SceneOptions(num_rigs=2, arc_deg=arc, seed=0, wide_focal=WIDE_FOCAL)
    dataset = render_dataset(work / "scene", options, overwrite=True)
    row: dict = {"arc_deg": arc, "sift": attempt(dataset, work / "sift", RunOptions(overwrite=True))}
    if asift:
        row["asift"] = attempt(dataset, work / "asift",
                               RunOptions(overwrite=True, matching=MatchingOptions(features=Features.ASIFT)))
    arena, truth = build_arena(options), dataset.load_ground_truth()
    for n in clicks:
        runs = []
        for seed in range(click_sets):
            try:
                rows = simulate_clicks(arena, truth, A, B, n=n, seed=seed).rows
            except ValueError as error:
                runs.append({"ok": False, "error": str(error)})
                continue
            csv = write_manual_matches(work / f"clicks_{n}_{seed}.csv", rows)
            # A fresh workspace per click set: its SIFT matches are merged with the clicks.
            runs.append(attempt(dataset, work / f"clicks_{n}_{seed}", RunOptions(overwrite=True, manual_matches=csv)))
            shutil.rmtree(work / f"clicks_{n}_{seed}", ignore_errors=True)
        row[f"clicks_{n}"] = runs
    return row


def _cell(result: dict) -> str:
    if not result["ok"]:
        return "fails: " + result["error"].split(":")[0][:60]
    text = f"{result['narrow_rotation_error_deg']:.3f}°"
    flagged = [w.split(":")[0] for w in result["warnings"] if w.split(":")[0] in ("POSE AMBIGUOUS",
                                                                                  "SCALE MEASUREMENTS DISAGREE")]
    return text + (f" ({', '.join(flagged)})" if flagged else "")


def _clicks_cell(runs: list[dict], reference: float | None) -> str:
    errors = [r["narrow_rotation_error_deg"] for r in runs if r["ok"]]
    if not errors:
        return "refused: " + runs[0]["error"][:60] if runs else "-"
    median = float(np.median(errors))
    ratio = f", {median / reference:.1f}x" if reference else ""
    return (f"median {median:.3f}°{ratio}, p90 {np.percentile(errors, 90):.3f}° "
            f"({len(errors)}/{len(runs)} registered)")


def markdown(rows: list[dict], clicks: list[int], asift: bool) -> str:
    first = rows[0]["sift"]  # the closest rigs: the reference where SIFT works
    reference = first["narrow_rotation_error_deg"] if first["ok"] and not first["warnings"] else None
    head = ["rigs apart", "SIFT"] + (["ASIFT"] if asift else []) + [f"{n} clicks" for n in clicks]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for row in rows:
        cells = [f"{row['arc_deg']:g}°", _cell(row["sift"])] + ([_cell(row["asift"])] if asift else [])
        cells += [_clicks_cell(row[f"clicks_{n}"], reference) for n in clicks]
        lines.append("| " + " | ".join(cells) + " |")
    note = (f"\nNarrow relative-rotation error against the exact ground truth; ratios are to SIFT at "
            f"{rows[0]['arc_deg']:g}° ({reference:.3f}°). Clicks are merged with whatever SIFT matched.\n"
            if reference else "\n")
    return "\n".join(lines) + "\n" + note


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arcs", type=float, nargs="+", default=[60, 90, 120, 140, 150, 160, 170])
    parser.add_argument("--clicks", type=int, nargs="+", default=[34, 60, 100])
    parser.add_argument("--click-sets", type=int, default=10)
    parser.add_argument("--asift", action="store_true")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    work = args.work or Path(tempfile.mkdtemp(prefix="rigsfm_separation_"))
    rows = []
    for arc in args.arcs:
        rows.append(separation(arc, work / f"arc{arc:g}", args.clicks, args.click_sets, args.asift))
        print(f"{arc:g} deg done", flush=True)
        write_json_atomic(args.out / "separation.json", {"wide_focal_px": WIDE_FOCAL, "rows": rows})
        write_text_atomic(args.out / "separation.md", markdown(rows, args.clicks, args.asift))
    print(markdown(rows, args.clicks, args.asift))
    return 0


if __name__ == "__main__":
    sys.exit(main())
