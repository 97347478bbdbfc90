"""Refine the calibration or hold it: the default adjustment against ``--fixed-calibration`` on weak and strong
networks.

    python benchmarks/hold_or_refine.py [--work DIR] [--scenes NAME ...] [--click-sets 3] [--out FILE]

Scenes (rendered arenas at 1624x1234 with the realistic calibration error in rigs.yaml, and its sigmas):

- ``clicks150_s<seed>``: 2 rigs 150 deg apart, wide f = 500 px (``benchmarks/separation.py``'s pair), SIFT merged
  with 34 simulated clicks (``rigsfm.synth.clicks``: 1 px noise, 20 % gross outliers), one run per click set;
- ``clicksonly150_s<seed>``: the same scene registered from the clicks alone (no SIFT matches: the paper's case);
- ``r2_60_s<seed>``: 2 rigs 60 deg apart; ``r3_120``: 3 rigs over 120 deg; ``demo``: ``rigsfm demo``'s 8-rig circle.

Each scene is rendered and mapped once (cached under WORK); the default adjustment (``AdjustOptions()``) and the
fixed one then start from the same mapping model. Two more variants: every rig's calibration refined
(``held_rigs=frozenset()``: the default before the hold-or-refine test), and every rig's held in the same
adjustment (measurements inside it, unlike ``--fixed-calibration``'s fitted scale). Scores against the exact ground
truth: the largest narrow relative-rotation error (deg) and the 95th percentile of the true epipolar distance (px;
true floor points of narrow i, their true correspondences in narrow j against the estimated epipolar lines,
``uncertainty.correspondence_check``), worst pair. Prints one table (ratios to fixed) and writes OUT (JSON).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import zlib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

from benchmarks.trust import true_floor_points  # noqa: E402
from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

logger = logging.getLogger("benchmarks.hold_or_refine")
A, B = "rig01/wide/frame0000.png", "rig02/wide/frame0000.png"


def scenes(click_sets: int, scene_seeds: int = 3) -> dict[str, tuple[SceneOptions, list[int | None]]]:
    """name -> (scene, click seeds; None: SIFT only)."""
    return {
        **{f"clicks150_s{seed}": (SceneOptions(num_rigs=2, arc_deg=150, seed=seed, wide_focal=500.0),
                                  list(range(click_sets))) for seed in range(scene_seeds)},
        **{f"clicksonly150_s{seed}": (SceneOptions(num_rigs=2, arc_deg=150, seed=seed, wide_focal=500.0),
                                      list(range(click_sets))) for seed in range(scene_seeds)},
        **{f"r2_60_s{seed}": (SceneOptions(num_rigs=2, arc_deg=60, seed=seed), [None])
           for seed in range(scene_seeds)},
        "r3_120": (SceneOptions(num_rigs=3, arc_deg=120, seed=0), [None]),
        "demo": (SceneOptions(), [None]),
    }


def mapped_model(root: Path, options: SceneOptions, click_seed: int | None, clicks: int = 34):
    """Render (once) and map (once per click set); returns (dataset, inputs, mapping model) or the error."""
    from rigsfm.core.workspace import Workspace, colmap_log_to
    from rigsfm.run.inputs.database import create_database
    from rigsfm.run.mapping.mapper import run_mapping
    from rigsfm.run.matching.extract import extract_features
    from rigsfm.run.matching.manual_matches import (
        read_manual_matches,
        validate_manual_matches,
        write_manual_matches,
    )
    from rigsfm.run.matching.manual_merge import add_manual_matches
    from rigsfm.run.matching.match import match_features
    from rigsfm.run.options import MappingOptions, MatchingOptions
    from rigsfm.run.pipeline import load_inputs
    from rigsfm.synth.clicks import simulate_clicks
    from rigsfm.synth.dataset import SyntheticDataset, render_dataset
    from rigsfm.synth.scene import build_arena

    scene_dir = root / "scene"
    if (scene_dir / "ground_truth").is_dir():  # rendered by an earlier call
        dataset = SyntheticDataset(scene_dir, scene_dir / "images", scene_dir / "rigs.yaml",
                                   scene_dir / "rigs_exact.yaml", scene_dir / "scale.yaml",
                                   scene_dir / "ground_truth", options, ())
    else:
        dataset = render_dataset(scene_dir, options, overwrite=True)
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)
    run_dir = root / ("run" if click_seed is None else f"run_clicks{click_seed}")
    model_dir = run_dir / "mapping"
    if (run_dir / "error.txt").exists():
        return dataset, inputs, (run_dir / "error.txt").read_text()
    if not model_dir.is_dir():
        workspace = Workspace(run_dir)
        workspace.root.mkdir(parents=True, exist_ok=True)
        matching = MatchingOptions()
        try:
            with colmap_log_to(workspace.colmap_log):
                create_database(workspace.database, inputs.rigs, inputs.images)
                extract_features(workspace.database, inputs.image_dir, inputs.images, matching)
                if not root.name.startswith("clicksonly"):
                    match_features(workspace.database, inputs.images, matching, workspace.pairs)
                few = False
                if click_seed is not None:
                    rows = simulate_clicks(build_arena(options), dataset.load_ground_truth(), A, B, n=clicks,
                                           seed=click_seed).rows
                    csv = write_manual_matches(run_dir / "clicks.csv", rows)
                    pairs = validate_manual_matches(csv, read_manual_matches(csv), inputs.images, inputs.rigs)
                    add_manual_matches(workspace.database, pairs, matching.max_error_px)
                    few = True
                num_wide = sum(e.sensor == "wide" for e in inputs.images)
                run_mapping(workspace, inputs.image_dir, MappingOptions(few_matches=few), num_wide=num_wide)
        except Exception as error:  # noqa: BLE001 - a scene that fails is recorded, not fatal
            (run_dir / "error.txt").write_text(repr(error))
            return dataset, inputs, repr(error)
    return dataset, inputs, pycolmap.Reconstruction(str(model_dir))


def cached_mapping_models(work: Path, names: list[str] | None = None, skip: set[str] = frozenset()):
    """The scenes of :func:`scenes` (3 click sets) already rendered and mapped under ``work``, in order: per mapping
    model ``(label, scene folder, dataset, inputs, mapping model)``, ``label`` the scene's name (and ``clicksN``);
    ``names``: only these scenes; ``skip``: labels left out before anything is read."""
    chosen = scenes(3)
    for name in names or list(chosen):
        options, seeds = chosen[name]
        for seed in seeds:
            label = name if seed is None else f"{name} clicks{seed}"
            run_dir = work / name / ("run" if seed is None else f"run_clicks{seed}")
            if label in skip or not (run_dir / "mapping").is_dir() or not (work / name / "scene").is_dir():
                continue
            yield (label, work / name, *mapped_model(work / name, options, seed))


def epipolar_p95(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> float | None:
    """The worst narrow pair's 95th percentile of the true epipolar distance (px)."""
    from rigsfm.core.geometry import correspondence_check
    from rigsfm.run.deliver import narrow_images

    names = sorted(im.name for im in narrow_images(estimate))
    worst = None
    for k, name_i in enumerate(names):
        for name_j in names[k + 1:]:
            for a, b in ((name_i, name_j), (name_j, name_i)):
                rng = np.random.default_rng(zlib.crc32(f"{a}|{b}".encode()))
                distances = correspondence_check(estimate, truth, a, b, true_floor_points(truth, a, rng))
                if len(distances) < 10:
                    continue
                p95 = float(np.quantile(distances, 0.95))
                worst = p95 if worst is None else max(worst, p95)
    return worst


def measure(name: str, options: SceneOptions, click_seed: int | None, work: Path) -> dict:
    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.options import AdjustOptions, Calibration
    from rigsfm.synth.truth import compare_to_ground_truth

    dataset, inputs, mapped = mapped_model(work / name, options, click_seed)
    row: dict = {"scene": name, "click_seed": click_seed}
    if isinstance(mapped, str):
        row["error"] = mapped
        return row
    truth = dataset.load_ground_truth()
    row["frames"] = mapped.num_reg_frames()
    for variant, adjust_options, held in (("fixed", AdjustOptions(calibration=Calibration.FIXED), None),
                                          ("refine_all", AdjustOptions(), frozenset()),
                                          ("hold_all", AdjustOptions(), frozenset(r.name for r in inputs.rigs)),
                                          ("default", AdjustOptions(), None)):
        t = time.perf_counter()
        result = adjust(mapped, inputs.rigs, inputs.scale, adjust_options, inputs.priors, with_covariance=True,
                        held_rigs=held)
        rec = result.reconstruction
        accuracy = compare_to_ground_truth(rec, truth, "narrow")
        row[variant] = {"narrow_rotation_deg": accuracy["relative_rotation_deg"]["max"],
                        "epipolar_p95_px": epipolar_p95(rec, truth), "seconds": time.perf_counter() - t,
                        "decisions": [vars(d) for d in result.decisions]}
    return row


def _cell(row: dict, variant: str) -> str:
    v, f = row[variant], row["fixed"]
    text = f"{v['narrow_rotation_deg']:.3f}°, {v['epipolar_p95_px']:.1f} px"
    if variant == "fixed":
        return text
    return (text + f" ({v['narrow_rotation_deg'] / f['narrow_rotation_deg']:.2f}x, "
            f"{v['epipolar_p95_px'] / f['epipolar_p95_px']:.2f}x)")


def table(rows: list[dict]) -> str:
    lines = ["| scene | fixed: rotation, epipolar p95 | refine all (before) | default (refine or hold) | held |",
             "| --- | --- | --- | --- | --- |"]
    for row in rows:
        label = row["scene"] + ("" if row["click_seed"] is None else f" (clicks {row['click_seed']})")
        if "error" in row:
            lines.append(f"| {label} | fails: {row['error'][:60]} | | | |")
            continue
        held = [d["rig"] for d in row["default"]["decisions"] if d["held"]]
        total = len(row["default"]["decisions"])
        lines.append(f"| {label} | {_cell(row, 'fixed')} | {_cell(row, 'refine_all')} | {_cell(row, 'default')} | "
                     f"{len(held)} of {total} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "benchmarks" / "results" / "hold_or_refine")
    parser.add_argument("--scenes", nargs="*", default=None)
    parser.add_argument("--click-sets", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s %(levelname)s %(message)s")
    logging.getLogger("rigsfm.run.adjustment.adjust").setLevel(logging.INFO)
    chosen = scenes(args.click_sets)
    names = args.scenes or list(chosen)
    rows = []
    for name in names:
        options, seeds = chosen[name]
        for seed in seeds:
            t = time.perf_counter()
            rows.append(measure(name, options, seed, args.work))
            print(f"{name} {seed}: {time.perf_counter() - t:.0f} s", flush=True)
            write_json_atomic(args.out or args.work / "hold_or_refine.json", {"rows": rows})
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
