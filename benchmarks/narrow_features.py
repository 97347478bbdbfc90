"""``--narrow-features`` against wide-only on a full circle with textured narrow views.

    python benchmarks/narrow_features.py WORK [--num-rigs 12] [--image-scale 0.5] [--seed 0] [--out results.json]

Renders ``SceneOptions(num_rigs, textured_centre=True, image_scale, seed)`` into ``WORK/scene`` (reused when
there), runs ``rigsfm.run.pipeline.run`` without and with ``narrow_features`` into ``WORK/wide`` and
``WORK/narrow`` (fresh each time), and prints per variant: the time per stage and in all, the mapper used,
the warnings, and the narrow cameras' accuracy against the exact ground truth next to the oracle's
(``rigsfm.synth.demo.score``). The table in benchmarks/README.md ("Narrow features") comes from it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from rigsfm.run.options import MatchingOptions, RunOptions
from rigsfm.run.pipeline import run
from rigsfm.synth.dataset import SyntheticDataset, render_dataset
from rigsfm.synth.demo import score
from rigsfm.synth.scene import SceneOptions

METRICS = ("relative_rotation_deg", "translation_direction_deg", "distance_error_percent")


def _scene(work: Path, options: SceneOptions) -> SyntheticDataset:
    root = work / "scene"
    if (root / "scene.yaml").exists():
        return SyntheticDataset(root, root / "images", root / "rigs.yaml", root / "rigs_exact.yaml",
                                root / "scale.yaml", root / "ground_truth", options, ())
    return render_dataset(root, options)


def measure(dataset: SyntheticDataset, out: Path, narrow: bool) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    result = run(dataset.images, dataset.rigs, out, dataset.scale,
                 RunOptions(matching=MatchingOptions(narrow_features=narrow)))
    total = time.perf_counter() - start
    accuracy = score(result, dataset)

    def rounded(block: dict) -> dict:
        return {metric: {k: round(block[metric][k], 4) for k in ("median", "max")} for metric in METRICS}

    return {
        "narrow_features": narrow, "total_s": round(total, 1), "stages_s": result.summary.timings_s,
        "mapper": result.summary.mapping.used, "warnings": result.summary.warnings,
        "narrow_registered": accuracy["narrow"]["registered"],
        "narrow": rounded(accuracy["narrow"]), "oracle": rounded(accuracy["oracle_narrow"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--num-rigs", type=int, default=12)
    parser.add_argument("--image-scale", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    dataset = _scene(args.work, SceneOptions(num_rigs=args.num_rigs, textured_centre=True,
                                             image_scale=args.image_scale, seed=args.seed))
    rows = [measure(dataset, args.work / name, narrow) for name, narrow in (("wide", False), ("narrow", True))]
    for row in rows:
        print(json.dumps(row))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
