"""The sampled band against the linear one on rendered 3-rig networks (the question SAMPLED_BAND_MAX_FRAMES = 3
left open: at 3 synthetic rigs the sampled band covered 0.906, the linear 0.926, at 6x the time).

    python benchmarks/three_rig_bands.py [--seeds 0 1 2 ...] [--work DIR] [--jobs 2]   # default: seeds 0-23

Per seed: a 3-rig arc of 120 deg (image scale 0.5, featureless centre, the realistic calibration error of
benchmarks/trust.py's scenes in rigs.yaml), rendered and mapped once (``trust.prepare``, cached under --work), then
the default adjustment (calibration priors) and both bands of every narrow pair on the same estimate, scored with
``trust.score_bands`` (400 true floor points per pair, their true correspondences' distances from the estimated
epipolar lines against the band). Prints one table; writes WORK/three_rig_bands.json.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from benchmarks.trust import DEFAULT_WORK, Scene, load_prepared, prepare, score_bands  # noqa: E402
from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402


def scene(seed: int) -> Scene:
    return Scene(f"r3_s{seed}", "3 rigs 120 deg, featureless", SceneOptions(num_rigs=3, arc_deg=120.0,
                                                                             image_scale=0.5, seed=seed))


def measure(seed: int, work: Path) -> dict:
    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
    from rigsfm.run.world.analysis_floor import find_floor

    s = scene(seed)
    prepare(s, work)
    prepared = load_prepared(s, work)
    if isinstance(prepared, str):
        return {"seed": seed, "error": prepared}
    adjusted = adjust(prepared.mapped, prepared.inputs.rigs, prepared.inputs.scale, None, prepared.priors)
    out = {"seed": seed, "frames": adjusted.reconstruction.num_reg_frames()}
    for band, sampled in (("sampled", True), ("linear", False)):
        start = time.perf_counter()
        plane, source = find_floor(adjusted.reconstruction, adjusted.scale_spec)
        uncertainty = estimate_uncertainty(adjusted, sampled=sampled, floor=plane, floor_source=source)
        out[band] = {"seconds": time.perf_counter() - start,
                     "pairs": score_bands(adjusted.reconstruction, prepared.truth, uncertainty.bands)}
    return out


def table(results: list[dict]) -> str:
    lines = ["| band | networks | pairs | pooled coverage | pairs < 85 %: observed / predicted | band median (px) "
             "| band time per network (s) |", "|---|---|---|---|---|---|---|"]
    ok = [r for r in results if "error" not in r and r["frames"] == 3]
    for band in ("sampled", "linear"):
        pairs = [p for r in ok for p in r[band]["pairs"]]
        weights = np.array([p["num_true_points"] for p in pairs], float)
        coverage = np.array([p["coverage"] for p in pairs])
        predicted_below = np.mean([p["predicted_below_85"] for p in pairs])
        lines.append(
            f"| {band} | {len(ok)} | {len(pairs)} | {np.sum(weights * coverage) / np.sum(weights):.3f} "
            f"| {100 * np.mean(coverage < 0.85):.1f} % / {100 * predicted_below:.1f} % "
            f"| {np.median([p['band_px'] for p in pairs]):.2f} "
            f"| {np.median([r[band]['seconds'] for r in ok]):.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(24)))
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK)
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(measure, args.seeds, [args.work] * len(args.seeds)))
    skipped = [r for r in results if "error" in r or r["frames"] != 3]
    write_json_atomic(args.work / "three_rig_bands.json", results)
    print(table(results))
    if skipped:
        left_out = [(r["seed"], r.get("error", r.get("frames"))) for r in skipped]
        print(f"left out (not 3 registered frames, or failed): {left_out}")


if __name__ == "__main__":
    main()
