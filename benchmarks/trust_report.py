"""Tables of benchmarks/trust.py (WORK/results/<scene>.json -> markdown)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

VARIANTS = ("fixed", "refine")


def _load(work: Path, names: list[str]) -> list[dict]:
    out = []
    for name in names:
        path = work / "results" / f"{name}.json"
        if path.exists():
            out.append(json.loads(path.read_text()))
    return out


def _f(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return f"{value:.{digits}f}"


def coverage_table(results: list[dict]) -> str:
    groups = defaultdict(list)
    for r in results:
        if "error" not in r:
            groups[r["group"]].append(r)
    lines = ["| scenes | variant | pairs | pooled coverage | mean per pair | pairs >= 85 % | band median (px) | "
             "true distance median / p95 (px) | predicted P(pair < 85 %) | observed pairs < 85 % |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    total = {v: [] for v in VARIANTS}
    for group, rows in groups.items():
        for variant in VARIANTS:
            bands = [b for r in rows for b in r["variants"][variant]["bands"]]
            total[variant].extend(bands)
            lines.append(_coverage_row(f"{group} ({len(rows)})", variant, bands))
    for variant in VARIANTS:
        lines.append(_coverage_row(f"**all ({len(results)})**", variant, total[variant]))
    return "\n".join(lines)


def _coverage_row(label: str, variant: str, bands: list[dict]) -> str:
    if not bands:
        return f"| {label} | {variant} | 0 | – | – | – | – | – | – | – |"
    # pooled: every true point counts once
    inside = sum(b["coverage"] * b["num_true_points"] for b in bands)
    points = sum(b["num_true_points"] for b in bands)
    coverage = np.array([b["coverage"] for b in bands])
    return (f"| {label} | {variant} | {len(bands)} | {inside / points:.3f} | {coverage.mean():.3f} | "
            f"{np.mean(coverage >= 0.85):.2f} | {np.median([b['band_px'] for b in bands]):.2f} | "
            f"{np.median([b['true_median_px'] for b in bands]):.2f} / {np.median([b['true_p95_px'] for b in bands]):.2f} | "
            f"{np.mean([b['predicted_below_85'] for b in bands]):.3f} | {np.mean(coverage < 0.85):.3f} |")


def bins_table(results: list[dict]) -> str:
    groups = defaultdict(list)
    for r in results:
        if "error" not in r:
            groups[r["group"]].append(r)
    lines = ["| scenes | variant | < 50 % | 50-85 % | 85-95 % | >= 95 % |", "|---|---|---|---|---|---|"]
    for group, rows in groups.items():
        for variant in VARIANTS:
            c = np.array([b["coverage"] for r in rows for b in r["variants"][variant]["bands"]])
            lines.append(f"| {group} | {variant} | {np.sum(c < 0.5)} | {np.sum((c >= 0.5) & (c < 0.85))} | "
                         f"{np.sum((c >= 0.85) & (c < 0.95))} | {np.sum(c >= 0.95)} |")
    return "\n".join(lines)


def accuracy_table(results: list[dict]) -> str:
    lines = ["| scene | narrow obs | rotation median / max (deg): fixed | refine | oracle | refine / oracle median, max "
             "| distance error max (%): fixed / refine / oracle |",
             "|---|---|---|---|---|---|---|"]
    ratios = defaultdict(list)
    for r in results:
        if "error" in r:
            lines.append(f"| {r['scene']} | failed: {r['error'][:60]} | | | | | |")
            continue
        acc = {v: r["variants"][v]["accuracy"] for v in (*VARIANTS, "oracle")}

        def rot(v):
            a = acc[v]["relative_rotation_deg"]  # noqa: B023 - called within this iteration: this scene's acc
            return f"{a['median']:.3f} / {a['max']:.3f}"

        med = acc["refine"]["relative_rotation_deg"]["median"] / acc["oracle"]["relative_rotation_deg"]["median"]
        mx = acc["refine"]["relative_rotation_deg"]["max"] / acc["oracle"]["relative_rotation_deg"]["max"]
        ratios[r["group"]].append((med, mx, r["variants"]["refine"]["narrow_observations"] > 0))
        dist = " / ".join(f"{abs(acc[v]['distance_error_percent']['max']):.2f}" for v in (*VARIANTS, "oracle"))
        lines.append(f"| {r['scene']} | {r['variants']['refine']['narrow_observations']} | {rot('fixed')} | "
                     f"{rot('refine')} | {rot('oracle')} | {med:.2f}, {mx:.2f} | {dist} |")
    lines.append("")
    lines.append("| scenes | refine / oracle rotation: geometric mean of median, of max | worst scene (max) |")
    lines.append("|---|---|---|")
    for group, values in ratios.items():
        v = np.array([(a, b) for a, b, _ in values])
        lines.append(f"| {group} | {np.exp(np.mean(np.log(v[:, 0]))):.2f}, {np.exp(np.mean(np.log(v[:, 1]))):.2f} | "
                     f"{v[:, 1].max():.2f} |")
    return "\n".join(lines)


def circle_table(results: list[dict]) -> str:
    lines = ["| scene | measurements (two sides) | fixed: distance error max (%) | refine | oracle | refine residuals "
             "(%) |", "|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r or r.get("scale_file") != "scale_two_sides.yaml":
            continue
        acc = {v: r["variants"][v]["accuracy"] for v in (*VARIANTS, "oracle")}
        residuals = ", ".join(f"{m['residual_percent']:+.3f}" for m in r["variants"]["refine"]["measurements"])
        lines.append(f"| {r['scene']} | rig01-rig02, rig02-rig03 | "
                     + " | ".join(f"{abs(acc[v]['distance_error_percent']['max']):.2f}" for v in (*VARIANTS, "oracle"))
                     + f" | {residuals} |")
    return "\n".join(lines)


def runtime_table(results: list[dict]) -> str:
    lines = ["| scene | frames | points | narrow pairs with a band | fixed adjust (s) | refine adjust (s, rounds) | "
             "covariance (s) | bands (s) |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            continue
        f, g = r["variants"]["fixed"], r["variants"]["refine"]
        lines.append(f"| {r['scene']} | {r['frames']} | {r['points']} | {len(g['bands'])} | {f['adjust_s']:.1f} | "
                     f"{g['adjust_s']:.1f} ({g['rounds']}) | {_f(g['covariance_s'], 1)} | {_f(g['bands_s'], 1)} |")
    return "\n".join(lines)


def write_report(work: Path, names: list[str], measured: Path | None = None) -> str:
    """The tables of WORK/results (or of ``measured``, a saved copy: benchmarks/measured_trust.json), also written
    to WORK/trust.md."""
    if measured is not None:
        saved = json.loads(Path(measured).read_text())
        results = [saved[n] for n in names if n in saved]
    else:
        results = _load(work, names)
    text = "\n\n".join([
        "## Band coverage of true floor correspondences", coverage_table(results),
        "## Per-pair coverage: number of pairs per bin", bins_table(results),
        "## Narrow accuracy against the fixed-calibration oracle", accuracy_table(results),
        "## 4-rig circles with two rangefinder distances", circle_table(results),
        "## Runtime (2 shared cores, niced)", runtime_table(results)]) + "\n"
    (work / "trust.md").write_text(text)
    return text
