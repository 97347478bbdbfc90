"""The floor from known-length markers alone (``rigsfm.run.world.floor_fit.marker_floor``): does its reported tilt
sigma cover the truth? Synthetic rings of N rigs (tests/synthetic_world.py, 0.5 deg camera rolls, nothing below the
cameras but one 2 m bar on the floor at a random place and direction): the tilt against the exact floor, within
1.96 ``normal_sigma_deg``; every camera's height within 1.96 ``camera_height_sigma``.

    python benchmarks/marker_floor.py [--seeds 80] [--rigs 4,6,8] [--bars 1|2] [--end-noise-mm 0]

``--bars 2``: a second 2 m bar 3-6 m from the first; ``--end-noise-mm``: Gaussian error of each triangulated end
(the rendered 6-rig crowd's bar ends lay 6.5-7 mm from the floor).

``--level``: how sloped a level bar on the floor looks along the cameras' up at its worst direction (the up's error),
against ``SCALE MARKER``'s tolerance (``rigsfm.run.adjustment.scale_check.LEVEL_TOLERANCE``), for 0.5-2 deg rolls.
"""

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synthetic_world import ring

from rigsfm.run.world.floor import estimate_floor


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=80)
    parser.add_argument("--rigs", default="4,6,8")
    parser.add_argument("--level", action="store_true")
    parser.add_argument("--bars", type=int, default=1, choices=(1, 2))
    parser.add_argument("--end-noise-mm", type=float, default=0.0)
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    if args.level:
        level(40)
        return
    print("| rigs | rings | tilt within 1.96 sigma | tilt / sigma median, p95 | heights within 1.96 sigma |")
    print("| --- | --- | --- | --- | --- |")
    for rigs in (int(r) for r in args.rigs.split(",")):
        inside = heights_in = heights = 0
        ratios = []
        for seed in range(14, 14 + args.seeds):
            world = ring(seed=seed, num_rigs=rigs, floor_points=0, wall_points=0, box_points=0, pillar_points=0)
            rng = np.random.default_rng(seed)
            start, angle = rng.uniform(-5, 5, 2), rng.uniform(0, np.pi)
            ends = [start, start + 2.0 * np.array([np.cos(angle), np.sin(angle)])]
            if args.bars == 2:
                away, turn = rng.uniform(0, 2 * np.pi), rng.uniform(0, np.pi)
                second = start + rng.uniform(3, 6) * np.array([np.cos(away), np.sin(away)])
                ends += [second, second + 2.0 * np.array([np.cos(turn), np.sin(turn)])]
            true_ends = np.array([[x, y, 0.0] for x, y in ends])
            true_ends += rng.normal(0.0, args.end_noise_mm / 1000.0, true_ends.shape)
            markers = np.array([world.model_from_truth * p for p in true_ends])
            fit = estimate_floor(world.reconstruction, None, markers).fit
            up = world.model_from_truth.rotation.matrix() @ np.array([0.0, 0.0, 1.0])
            tilt = float(np.degrees(np.arccos(np.clip(fit.normal @ up, -1.0, 1.0))))
            inside += tilt < 1.96 * fit.normal_sigma_deg
            ratios.append(tilt / fit.normal_sigma_deg)
            for name, height in world.truth_heights.items():
                heights += 1
                heights_in += abs(fit.camera_heights[name] - height) < 1.96 * fit.height_sigma
        print(f"| {rigs} | {args.seeds} | {inside}/{args.seeds} | {np.median(ratios):.2f}, "
              f"{np.percentile(ratios, 95):.2f} | {heights_in}/{heights} |")


def level(seeds: int) -> None:
    from rigsfm.run.adjustment.scale_check import LEVEL_TOLERANCE
    from rigsfm.run.world.floor_model import up_prior

    print(f"| rolls (deg) | rigs | slope median | p95 | max | above {LEVEL_TOLERANCE:.0%} |")
    print("| --- | --- | --- | --- | --- | --- |")
    for roll in (0.5, 1.0, 2.0):
        for rigs in (3, 4, 6, 8):
            slopes = []
            for seed in range(seeds):
                world = ring(seed=seed, num_rigs=rigs, roll_deg=roll, floor_points=0, wall_points=0, box_points=0,
                             pillar_points=0)
                up, _ = up_prior(world.reconstruction)
                true_up = world.model_from_truth.rotation.matrix() @ np.array([0.0, 0.0, 1.0])
                slopes.append(np.sin(np.arccos(np.clip(up @ true_up, -1.0, 1.0))))
            s = np.array(slopes)
            print(f"| {roll} | {rigs} | {np.median(s):.3f} | {np.percentile(s, 95):.3f} | {s.max():.3f} | "
                  f"{int((s > LEVEL_TOLERANCE).sum())}/{seeds} |")


if __name__ == "__main__":
    main()
