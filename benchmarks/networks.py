"""Twenty-odd rendered networks, each run as a user runs it and with ``--fixed-calibration``, scored against the
exact truth: narrow accuracy, the delivered band's coverage and width, run time, and the frame offsets' error.

    python benchmarks/networks.py WORK [--only NAME ...] [--force] [--out FILE] [--report] [--default-only]
    python benchmarks/networks.py WORK --measured benchmarks/measured_networks.json   # the saved tables again

Networks (``networks()``; rendered once into ``WORK/<name>/scene`` by ``rigsfm.synth`` at ``--image-scale 0.5``,
812x617, to keep 20 of them affordable on 2 cores; realistic calibration error in rigs.yaml with its sigmas): 2-16
rigs on full circles and arcs of 30-180 deg; featureless centres (``plain``), a crowd texture painted on the floor
(``flat``), and crowds of 3D persons (``persons``: 4 per m2, heads at 1.5-1.9 m, occluding bodies, walking between
frames; 2 synchronised frames per rig); and persons recordings whose rigs are shifted by known frame offsets
(``shift``: synth ``frame_offsets``; run with ``--frame-offsets auto``), one of them synchronised as a control.

Per network, three results:

- ``default``: ``rigsfm.run.pipeline.run`` with the default options (``--narrow auto``, hold or refine), fresh;
- ``fixed``: the same with ``--fixed-calibration`` (the oracle issue 34 names), its features and matches reused from
  ``default``'s workspace (so its wall time is not a full run's);
- ``oracle``: ``rigsfm.synth.truth.oracle``, the fixed-calibration adjustment started from the true poses with the
  ``fixed`` run's observations (narrow accuracy only).

``--default-only`` runs ``default`` alone (results under ``WORK/results_default``, the table of its hold-or-refine
decisions on stdout): the sweep of ``CALIBRATION CONTRADICTED``'s false alarms.

Scores (``benchmarks.metrics.evaluate``, ``benchmarks.trust.score_bands``, ``benchmarks.hold_or_refine.epipolar_p95``):
narrow relative-rotation error median / max (deg, every narrow pair), the worst pair's 95th percentile of the true
epipolar distance (px, true floor points), per pair the delivered ``epipolar_band_95_px`` against 400 true floor
correspondences (pooled coverage, band median, median of band / true p95), CPU seconds (summary.json ``cpu_s``, all
stages) and wall seconds, what ``--narrow auto`` decided, the self-check's verdicts, the hold-or-refine decisions
(``decisions_record``), and for ``shift`` networks each rig's estimated offset (summary.json ``frame_offsets``)
against the truth. Results: ``WORK/results/<name>.json``
(kept: a rerun skips scored networks unless ``--force``; workers started side by side share the list, each
network measured by the first to claim it), all of them in ``--out`` (default ``WORK/networks.json``),
and a markdown table on stdout.
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
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

logger = logging.getLogger("benchmarks.networks")
SCALE = 0.5


@dataclass(frozen=True)
class Network:
    name: str
    kind: str  # plain, flat, persons, shift
    options: SceneOptions


def networks() -> dict[str, Network]:
    """Cheapest first, so that a run cut short has scored the most networks."""

    def net(name: str, kind: str, **options) -> Network:
        if kind in ("persons", "shift"):
            options.setdefault("persons_per_m2", 4.0)
            options.setdefault("frames_per_rig", 2)
        return Network(name, kind, SceneOptions(image_scale=SCALE, textured_centre=kind == "flat", **options))

    out = [
        net("plain2_60_s0", "plain", num_rigs=2, arc_deg=60, seed=0),
        net("plain2_60_s1", "plain", num_rigs=2, arc_deg=60, seed=1),
        net("flat2_60_s0", "flat", num_rigs=2, arc_deg=60, seed=0),
        net("persons2_30_s0", "persons", num_rigs=2, arc_deg=30, seed=0),
        net("persons3_60_s1", "persons", num_rigs=3, arc_deg=60, seed=1),
        net("shift3_30_s0", "shift", num_rigs=3, arc_deg=30, seed=0, frames_per_rig=3,
            frame_offsets=(("rig03", 1.0),)),
        net("plain4_360_s0", "plain", num_rigs=4, seed=0),
        net("flat4_135_s0", "flat", num_rigs=4, arc_deg=135, seed=0),
        net("persons4_135_s0", "persons", num_rigs=4, arc_deg=135, seed=0),
        net("persons4_90_s0", "persons", num_rigs=4, arc_deg=90, seed=0),
        net("shift4_60_sync_s1", "shift", num_rigs=4, arc_deg=60, seed=1, frames_per_rig=3),
        net("shift4_60_s1", "shift", num_rigs=4, arc_deg=60, seed=1, frames_per_rig=3,
            frame_offsets=(("rig02", 1.0),)),
        net("shift5_80_s2", "shift", num_rigs=5, arc_deg=80, seed=2, frames_per_rig=3,
            frame_offsets=(("rig02", 1.0), ("rig04", -1.0))),
        net("plain6_180_s1", "plain", num_rigs=6, arc_deg=180, seed=1),
        net("flat6_360_s1", "flat", num_rigs=6, seed=1),
        net("plain8_360_s0", "plain", num_rigs=8, seed=0),
        net("flat8_360_s0", "flat", num_rigs=8, seed=0),
        net("persons8_360_s0", "persons", num_rigs=8, seed=0),
        net("persons8_360_s1", "persons", num_rigs=8, seed=1),
        net("plain12_360_s2", "plain", num_rigs=12, seed=2),
        net("flat12_360_s1", "flat", num_rigs=12, seed=1),
        net("plain16_360_s0", "plain", num_rigs=16, seed=0),
    ]
    return {n.name: n for n in out}


def dataset(network: Network, work: Path):
    from rigsfm.synth.dataset import SyntheticDataset, render_dataset

    root = work / network.name / "scene"
    if (root / "ground_truth").is_dir() and (root.parent / "rendered.json").exists():
        return SyntheticDataset(root, root / "images", root / "rigs.yaml", root / "rigs_exact.yaml",
                                root / "scale.yaml", root / "ground_truth", network.options, ())
    start = time.perf_counter()
    data = render_dataset(root, network.options, overwrite=True)
    write_json_atomic(root.parent / "rendered.json", {"render_s": time.perf_counter() - start})
    return data


def default_mapping_models(work: Path, names: list[str], skip: set[str] = frozenset()):
    """Per network of ``names`` whose default run left its mapping model under ``work`` (and not in ``skip``):
    ``(name, inputs, ground truth, the default run's mapping model)``, read only."""
    from rigsfm.run.pipeline import load_inputs

    for name in names:
        net = work / name
        if name in skip or not (net / "default" / "mapping").is_dir():
            continue
        scene = net / "scene"
        yield (name, load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml"),
               pycolmap.Reconstruction(str(scene / "ground_truth")),
               pycolmap.Reconstruction(str(net / "default" / "mapping")))


def score(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, summary: dict) -> dict:
    """Narrow accuracy and the delivered bands against the truth."""
    from benchmarks.hold_or_refine import epipolar_p95
    from benchmarks.metrics import evaluate
    from benchmarks.trust import score_bands

    narrow = evaluate(rec, truth, metric=True)["narrow"]
    bands = {(p["i"], p["j"]): SimpleNamespace(band_px=p["band_px"], points=p["points"],
                                               predicted_below_85=p["predicted_below_85"],
                                               predicted_coverage=np.array([0.0]))  # not in summary.json
             for p in (summary.get("uncertainty") or {}).get("pairs", []) if p.get("band_px") is not None}
    rows = score_bands(rec, truth, bands)
    for row in rows:
        row.pop("predicted_coverage_mean")
    counted = sum(r["num_true_points"] for r in rows)
    return {
        "registered": narrow.get("registered"), "total": narrow.get("total"),
        "rotation_deg": {k: narrow["relative_rotation_deg"][k] for k in ("median", "max")}
        if narrow.get("relative_rotation_deg") else None,
        "distance_percent": narrow.get("distance_error_percent"),
        "true_epipolar_p95_px": epipolar_p95(rec, truth),
        "pairs_scored": len(rows),
        "coverage": float(sum(r["coverage"] * r["num_true_points"] for r in rows) / counted) if counted else None,
        "band_median_px": float(np.median([r["band_px"] for r in rows])) if rows else None,
        "true_p95_median_px": float(np.median([r["true_p95_px"] for r in rows])) if rows else None,
        "band_over_true_p95_median": float(np.median([r["band_px"] / r["true_p95_px"] for r in rows
                                                      if r["true_p95_px"] > 0])) if rows else None,
        "bands": rows,
    }


def offset_errors(network: Network, summary: dict) -> dict | None:
    """Each rig's estimated offset against the truth, both relative to their median (the gauge of offsets)."""
    record = summary.get("frame_offsets") or {}
    estimate = (record.get("estimate") or {}).get("offsets")
    if network.kind != "shift" or estimate is None:
        return None if network.kind != "shift" else {"estimated": None, "applied": record.get("applied")}
    true = {f"rig{i + 1:02d}": network.options.frame_offset(f"rig{i + 1:02d}") for i in range(network.options.num_rigs)}
    told = {r: o for r, o in estimate.items() if o is not None}
    errors = {}
    if told:
        shift = float(np.median([told[r] - true[r] for r in told]))
        errors = {r: told[r] - true[r] - shift for r in told}
    return {"true": true, "estimated": estimate, "applied": record.get("applied"),
            "unsynchronised": record["estimate"].get("unsynchronised"),
            "rigs_told": len(told), "rigs": len(true),
            "max_abs_error_frames": max((abs(e) for e in errors.values()), default=None)}


def decisions_record(summary: dict) -> dict:
    """The run's hold-or-refine decisions (summary.json ``calibration_decisions``): the network's consistency test
    (chi-square, dof, its HOLD_QUANTILE and CONTRADICTED_QUANTILE limits), the rigs refined, and whether the
    ``CALIBRATION CONTRADICTED`` warning is among summary.json's ``warnings``."""
    from scipy.stats import chi2

    from rigsfm.run.adjustment.decisions import CONTRADICTED_QUANTILE, HOLD_QUANTILE

    decisions = summary.get("calibration_decisions") or []
    tested = [d for d in decisions if d.get("network_dof")]
    dof = tested[0]["network_dof"] if tested else 0
    return {"rigs": len(decisions), "refined": [d["rig"] for d in decisions if not d["held"]],
            "network_chi2": tested[0]["network_chi2"] if tested else None, "network_dof": dof,
            "limit_hold": float(chi2.ppf(HOLD_QUANTILE, dof)) if dof else None,
            "limit_contradicted": float(chi2.ppf(CONTRADICTED_QUANTILE, dof)) if dof else None,
            "contradicted": any(w.startswith("CALIBRATION CONTRADICTED") for w in summary.get("warnings", [])),
            "per_rig": [{k: d.get(k) for k in ("rig", "held", "chi2", "dof", "limit", "largest_gain", "reason")}
                        for d in decisions]}


def run_one(network: Network, data, out: Path, fixed: bool, reuse: Path | None) -> tuple[dict, pycolmap.Reconstruction]:
    from rigsfm.run.options import AdjustOptions, Calibration, RunOptions, SelfCheckOptions
    from rigsfm.run.pipeline import run

    shutil.rmtree(out, ignore_errors=True)
    if reuse is not None:  # features and matches of the default run (same settings): only what follows is redone
        shutil.copytree(reuse, out)
    options = RunOptions(overwrite=reuse is not None,
                         adjust=AdjustOptions(calibration=Calibration.FIXED if fixed else Calibration.REFINE),
                         self_check=SelfCheckOptions(frame_offsets="auto" if network.kind == "shift" else None))
    start = time.perf_counter()
    result = run(data.images, data.rigs, out, data.scale, options)
    wall = time.perf_counter() - start
    summary = json.loads(result.workspace.summary.read_text(encoding="utf-8"))
    truth = pycolmap.Reconstruction(str(data.ground_truth))
    record = summary.get("narrow_observations") or {}
    checks: dict[str, int] = {}
    for p in (summary.get("epipolar_self_check") or {}).get("pairs", []):
        checks[p["verdict"]] = checks.get(p["verdict"], 0) + 1
    row = {"wall_s": wall, "cpu_s": sum(summary["cpu_s"].values()), "timings_s": summary["timings_s"],
           "features_reused": reuse is not None, "narrow_used": record.get("used"),
           "narrow_observations": record.get("observations_added"), "self_check": checks,
           "warnings": len(summary.get("warnings", [])), "decisions": decisions_record(summary),
           **score(result.reconstruction, truth, summary), "frame_offsets": offset_errors(network, summary)}
    return row, result.reconstruction


def result_path(work: Path, name: str, default_only: bool = False) -> Path:
    """Where a network's result is kept: default-only results apart, so that a full measurement does not skip them."""
    return work / ("results_default" if default_only else "results") / f"{name}.json"


def measure(network: Network, work: Path, force: bool = False, default_only: bool = False) -> dict:
    from rigsfm.run.pipeline import load_inputs
    from rigsfm.synth.truth import compare_to_ground_truth, oracle

    path = result_path(work, network.name, default_only)
    if path.exists() and not force:
        return json.loads(path.read_text())
    t = time.perf_counter()
    data = dataset(network, work)
    result: dict = {"network": network.name, "kind": network.kind, "options": vars(network.options),
                    "render_s": json.loads((data.root.parent / "rendered.json").read_text())["render_s"]}
    logger.info("%s rendered (%.0f s)", network.name, time.perf_counter() - t)
    try:
        result["default"], _ = run_one(network, data, work / network.name / "default", False, None)
        logger.info("%s default: %s", network.name, _brief(result["default"]))
        if default_only:
            result["default_only"] = True
            write_json_atomic(path, result, overwrite=True)
            return result
        result["fixed"], fixed = run_one(network, data, work / network.name / "fixed", True,
                                         work / network.name / "default")
        logger.info("%s fixed: %s", network.name, _brief(result["fixed"]))
        inputs = load_inputs(data.images, data.rigs, data.scale)
        truth = pycolmap.Reconstruction(str(data.ground_truth))
        limit = compare_to_ground_truth(oracle(fixed, truth, inputs.rigs, inputs.scale), truth, "narrow")
        result["oracle"] = {"rotation_deg": {k: limit["relative_rotation_deg"][k] for k in ("median", "max")}}
    except Exception as error:  # noqa: BLE001 - a network that fails is recorded, not fatal
        logger.error("%s failed:\n%s", network.name, traceback.format_exc())
        result["error"] = f"{type(error).__name__}: {error}"
    write_json_atomic(path, result, overwrite=True)
    return result


def claim(folder: Path) -> bool:
    """Whether this process may measure the network in ``folder``: workers started side by side share the list."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "claimed"
    for _ in range(2):
        try:
            with open(path, "x") as f:
                f.write(str(os.getpid()))
            return True
        except FileExistsError:
            try:
                os.kill(int(path.read_text() or 0), 0)
                return False
            except (ProcessLookupError, ValueError):  # its worker is gone: take it over
                path.unlink(missing_ok=True)
    return False


def _brief(row: dict) -> str:
    rot = row["rotation_deg"] or {}
    return (f"rotation {rot.get('median')} / {rot.get('max')} deg, p95 {row['true_epipolar_p95_px']}, "
            f"coverage {row['coverage']}, band {row['band_median_px']}, cpu {row['cpu_s']:.0f} s, "
            f"wall {row['wall_s']:.0f} s")


def analysed(bands: list[dict]) -> list[dict]:
    """The pairs an analyst searches: two rigs, one frame name (a rig's own frames share its pose; frames of two
    times duplicate the synchronised pair)."""
    def rig_frame(name: str) -> tuple[str, str]:
        parts = name.split("/")
        return parts[0], parts[-1]

    out = []
    for band in bands:
        (rig_i, frame_i), (rig_j, frame_j) = (rig_frame(n) for n in band["pair"])
        if rig_i != rig_j and frame_i == frame_j:
            out.append(band)
    return out


def band_stats(bands: list[dict]) -> dict:
    """Pooled coverage, band median, true p95 median and median band / true p95 over ``analysed(bands)``."""
    rows = analysed(bands)
    counted = sum(r["num_true_points"] for r in rows)
    if not counted:
        return {"pairs": 0, "coverage": None, "band_median_px": None, "true_p95_median_px": None, "ratio_median": None}
    return {"pairs": len(rows),
            "coverage": sum(r["coverage"] * r["num_true_points"] for r in rows) / counted,
            "band_median_px": float(np.median([r["band_px"] for r in rows])),
            "true_p95_median_px": float(np.median([r["true_p95_px"] for r in rows])),
            "ratio_median": float(np.median([r["band_px"] / r["true_p95_px"] for r in rows if r["true_p95_px"] > 0]))}


def _f(value, digits: int = 3, suffix: str = "") -> str:
    return "-" if value is None else f"{value:.{digits}f}{suffix}"


def table(results: list[dict]) -> str:
    lines = ["| network | narrow used | rotation median / max (deg): default | fixed | oracle | true epipolar p95 (px): "
             "default / fixed | pairs | coverage | band median (px) | band / true p95 | CPU / wall (s) | offsets: true "
             "-> estimated (max error) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['network']} | fails: {r['error'][:80]} | | | | | | | | | | |")
            continue
        d, f = r["default"], r["fixed"]
        o = r.get("oracle", {}).get("rotation_deg") or {}
        offsets = "-"
        if d["frame_offsets"] is not None:
            fo = d["frame_offsets"]
            if fo.get("true") is None:
                offsets = "not estimated"
            else:
                shifted = {k: int(v) for k, v in fo["true"].items() if v} or "all 0"
                told = {k: v for k, v in fo["estimated"].items() if v}
                offsets = (f"{shifted} -> none told" if not fo["rigs_told"] else
                           f"{shifted} -> {told or 'all 0'}, {fo['rigs_told']}/{fo['rigs']} told"
                           f" (max error {_f(fo['max_abs_error_frames'], 0)})")
        b = band_stats(d["bands"])
        lines.append(
            f"| {r['network']} | {d['narrow_used']} | {_f(d['rotation_deg']['median'], 4)} / "
            f"{_f(d['rotation_deg']['max'], 4)} | {_f(f['rotation_deg']['median'], 4)} / {_f(f['rotation_deg']['max'], 4)}"
            f" | {_f(o.get('median'), 4)} / {_f(o.get('max'), 4)} | {_f(d['true_epipolar_p95_px'], 2)} / "
            f"{_f(f['true_epipolar_p95_px'], 2)} | {b['pairs']} | "
            f"{_f(100 * b['coverage'] if b['coverage'] is not None else None, 1, ' %')} | {_f(b['band_median_px'], 2)}"
            f" | {_f(b['ratio_median'], 2)} | {d['cpu_s']:.0f} / "
            f"{d['wall_s']:.0f} | {offsets} |")
    return "\n".join(lines)


def decisions_table(results: list[dict]) -> str:
    """Per network, the default run's network consistency test and whether it warned CALIBRATION CONTRADICTED."""
    lines = ["| network | rigs | dof | chi-square | 95 % limit | 99.9 % limit | held / refined | warned |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['network']} | fails: {r['error'][:80]} | | | | | | |")
            continue
        d = r["default"]["decisions"]
        state = ("refined" if len(d["refined"]) == d["rigs"] else "held" if not d["refined"]
                 else f"{len(d['refined'])} of {d['rigs']} refined")
        lines.append(f"| {r['network']} | {d['rigs']} | {d['network_dof']} | {_f(d['network_chi2'], 1)} | "
                     f"{_f(d['limit_hold'], 1)} | {_f(d['limit_contradicted'], 1)} | {state} | "
                     f"{'yes' if d['contradicted'] else 'no'} |")
    return "\n".join(lines)


def _stat(values: list[float]) -> str:
    if not values:
        return "- (no pair)"
    return (f"{np.median(values):.2f} (quartiles {np.quantile(values, 0.25):.2f}-{np.quantile(values, 0.75):.2f}, "
            f"{len(values)} pairs)")


def summary_lines(results: list[dict]) -> str:
    """Pooled numbers over the scored networks (the README's headline)."""
    ok = [r for r in results if "error" not in r]
    if not ok:
        return "no network scored"
    bands = [b for r in ok for b in analysed(r["default"]["bands"])]
    points = sum(b["num_true_points"] for b in bands)
    inside = sum(b["coverage"] * b["num_true_points"] for b in bands)
    ratios = [b["band_px"] / b["true_p95_px"] for r in ok if not r["default"]["narrow_used"]
              for b in analysed(r["default"]["bands"]) if b["true_p95_px"] > 0]
    used = [b["band_px"] / b["true_p95_px"] for r in ok if r["default"]["narrow_used"]
            for b in analysed(r["default"]["bands"]) if b["true_p95_px"] > 0]
    rot = [r["default"]["rotation_deg"]["max"] / r["fixed"]["rotation_deg"]["max"] for r in ok]
    epi = [r["default"]["true_epipolar_p95_px"] / r["fixed"]["true_epipolar_p95_px"] for r in ok
           if r["default"]["true_epipolar_p95_px"] and r["fixed"]["true_epipolar_p95_px"]]
    return (f"{len(ok)} networks, {len(bands)} pairs: pooled coverage "
            f"{100 * inside / points:.1f} %; band / true p95 median {_stat(ratios)} without narrow observations, "
            f"{_stat(used)} with them; default / fixed: max rotation "
            f"median {np.median(rot):.2f}x (worst {max(rot):.2f}x, {sum(x <= 1.0 for x in rot)} of {len(rot)} <= 1), "
            f"worst-pair epipolar p95 median {np.median(epi):.2f}x (worst {max(epi):.2f}x, "
            f"{sum(x <= 1.0 for x in epi)} of {len(epi)} <= 1)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--only", nargs="+", default=None, choices=sorted(networks()))
    parser.add_argument("--force", action="store_true", help="measure again networks already scored")
    parser.add_argument("--report", action="store_true", help="only the table of the networks already scored")
    parser.add_argument("--default-only", action="store_true",
                        help="the default run alone (no --fixed-calibration run, no oracle); results under "
                        "WORK/results_default, the decisions' table on stdout")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--measured", type=Path, default=None,
                        help="print the table and summary of this saved copy (benchmarks/measured_networks.json)")
    args = parser.parse_args()
    if args.measured:
        results = json.loads(args.measured.read_text())["results"]
        print(table(results))
        print()
        print(summary_lines(results))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        handlers=[logging.FileHandler(args.work / "networks.log"), logging.StreamHandler()])
    for noisy in ("rigsfm", "pycolmap"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    chosen = [networks()[n] for n in args.only] if args.only else list(networks().values())
    results = []
    for network in chosen:
        path = result_path(args.work, network.name, args.default_only)
        if args.report:
            if path.exists():
                results.append(json.loads(path.read_text()))
            continue
        if not path.exists() or args.force:
            if not claim(args.work / network.name):
                logger.info("%s: another worker measures it", network.name)
                continue
            t = time.perf_counter()
            try:
                measure(network, args.work, args.force, args.default_only)
            finally:
                (args.work / network.name / "claimed").unlink(missing_ok=True)
            logger.info("%s done in %.0f s", network.name, time.perf_counter() - t)
        results.append(json.loads(path.read_text()))
    write_json_atomic(args.out or args.work / "networks.json", {"results": results}, overwrite=True)
    if args.default_only:
        print(decisions_table(results))
        return
    print(table(results))
    print()
    print(summary_lines(results))


if __name__ == "__main__":
    main()
