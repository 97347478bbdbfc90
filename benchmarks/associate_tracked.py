"""Carried frames seeded by the frame before's persons against the full pair search: CPU and accuracy per frame.

    python benchmarks/associate_tracked.py DATASET OUT [--frames 4] [--seeds 2] [--static] [--step 1]
        [--walk 0.15] [--json F]

DATASET: a crowd rendered over several frames (``python -m rigsfm.synth --frames-per-rig T --frame-period-s 0.1``);
OUT: ``rigsfm run`` on its first frame (static rigs: every later frame's images take their camera's frame-0 pose,
band and centre covariance, as benchmarks/associate_video.py does). Detections per frame as benchmarks/associate.py
makes them (true visible heads, 1.5 px noise, 10 % missed, 5 % false; seed + 1000 k for frame k). ``--static``:
every frame is frame 0's heads (new noise, misses and false ones; benchmarks/associate_speed.py's carried frames);
``--step S``: the recording's frames 0, S, 2 S, ... (a lower frame rate).

Frame 0 self-calibrates once; then the later frames are associated as ``associate_frames`` carries them, once with
the earlier frame's persons as seeds (``walk_m``) and once with the full pair search (``walk_m=None``), each chain
carrying its own shifts and persons, the two run one after the other per frame (alternating which goes first) so the
machine's load falls on both alike. Per frame and chain: this process's CPU seconds, pair and person F1, the right
persons' head error and the share of them whose 95 % ellipsoid holds the true head, and how many persons the two
chains share.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # run as a script: the benchmarks package beside rigsfm

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

from benchmarks.associate import head_errors  # noqa: E402
from benchmarks.associate_video import video_model  # noqa: E402
from rigsfm.associate import AssociateOptions, from_arrays, load_run  # noqa: E402
from rigsfm.associate.evaluate import (  # noqa: E402
    make_detections,
    score_groups,
    true_heads,
    truth_from_run,
    visible_heads,
)
from rigsfm.associate.pipeline import frame_views  # noqa: E402
from rigsfm.associate.solve import associate_views  # noqa: E402


def accuracy(result, views, truth, heads3d: np.ndarray, r: np.ndarray, t: np.ndarray) -> dict:
    groups = [[(views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in result.members]
    scores = score_groups(groups, truth)
    errors, inside = head_errors(groups, result, truth, heads3d, r, t)
    return {"persons": len(result), "pair_f1": round(scores.pair_f1, 4), "person_f1": round(scores.person_f1, 4),
            "right": len(errors), "error_median_cm": round(100 * float(np.median(errors)), 2) if errors else None,
            "error_p95_cm": round(100 * float(np.percentile(errors, 95)), 2) if errors else None,
            "coverage_95": round(float(np.mean(inside)), 4) if inside else None}


def run_seed(dataset: Path, out: Path, seed: int, frames: int, static: bool, options: AssociateOptions,
             step: int = 1) -> list[dict]:
    model = video_model(load_run(out), dataset, 1 if static else (frames - 1) * step + 1)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    r, t = truth_from_run(pycolmap.Reconstruction(str(out / "sparse")),
                          pycolmap.Reconstruction(str(dataset / "ground_truth")))
    chains = {"tracked": options, "full": dataclasses.replace(options, walk_m=None)}
    state: dict[str, tuple] = {}
    rows = []
    for k in range(frames):
        source = 0 if static else k * step
        name = f"frame{source:04d}"
        heads = {n: v for n, v in visible_heads(dataset, name).items() if n in sizes}
        truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed + 1000 * k)
        detections = from_arrays(truth.points)
        heads3d = true_heads(dataset, source)
        order = list(chains) if k % 2 else list(chains)[::-1]
        results = {}
        for chain in order if k else ["full"]:
            views = frame_views(model, detections, name, sorted(detections.images))
            if k:
                for view, before in zip(views, state[chain][0]):
                    view.carry(before)
            wall, cpu = time.perf_counter(), time.process_time()
            result = associate_views(views, chains[chain], carried=k > 0, earlier=state[chain][1] if k else None)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            results[chain] = result
            state[chain] = (views, result)
            rows.append({"seed": seed, "frame": k, "chain": chain if k else "first", "cpu_seconds": round(cpu, 3),
                         "seconds": round(wall, 3), **accuracy(result, views, truth, heads3d, r, t)})
            print(json.dumps(rows[-1]), flush=True)
        if not k:
            state["tracked"] = (state["full"][0], state["full"][1])
            continue
        keys = {chain: [m.tobytes() for m in result.members] for chain, result in results.items()}
        same = set(keys["tracked"]) & set(keys["full"])
        row = {"seed": seed, "frame": k, "shared_persons": len(same)}
        for chain, result in results.items():  # the persons only one chain found: how many are right
            only = [m for m, key in zip(result.members, keys[chain]) if key not in same]
            ids = [{int(truth.person[views[v].name][i]) for v, i in enumerate(m) if i >= 0} for m in only]
            row[f"{chain}_only"] = len(only)
            row[f"{chain}_only_right"] = sum(len(p) == 1 and -1 not in p for p in ids)
        rows.append(row)
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=4, help="frames in all, the first self-calibrating")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--static", action="store_true", help="every frame is frame 0's heads")
    parser.add_argument("--step", type=int, default=1, help="the recording's frames 0, step, 2 step, ... (a lower "
                        "frame rate: the persons walk step times farther between two frames)")
    parser.add_argument("--walk", type=float, default=AssociateOptions().walk_m)
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    options = AssociateOptions(pixel_sigma=args.pixel_sigma, walk_m=args.walk)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rows += run_seed(args.dataset, args.out, seed, args.frames, args.static, options, args.step)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
