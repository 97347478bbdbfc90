"""A recording of static rigs associated frame after frame: each frame's pair F1 with and without associating again
the frames whose own crowd corrected none of their views (``AssociateOptions.revisit``), against the exact poses.

    python benchmarks/associate_recording.py DATASET OUT [--frames 8] [--seeds 0,1] [--alone] [--json F]

DATASET: a crowd rendered over several frames (``python -m rigsfm.synth --frames-per-rig 8 --frame-period-s 0.5``);
OUT: ``rigsfm run`` of its first frame only (every later frame takes its camera's frame-0 pose, band and centre
covariance: ``--poses-from frame0000.png``). Detections per frame as benchmarks/associate.py makes them (true visible
heads, 1.5 px noise, 10 % missed, 5 % false; seed + 1000 k for frame k). "Exact": the same association on the
truth's poses with the run's bands (a reference, not a result). ``--alone``: each frame also associated as a
recording of its own (does its crowd correct its views?). CPU: this process's seconds for the whole recording.
``--walks 0.15,auto,0``: instead, the recording (revisit on) at each walk (``auto``: the options' default; 0: every
pair searched).
benchmarks/README.md, "Nineteenth pass" and "The walk from the recording", have the numbers.
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

from benchmarks.associate import lend_poses  # noqa: E402
from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run  # noqa: E402
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads  # noqa: E402
from rigsfm.associate.pipeline import RunModel  # noqa: E402

# a fixed walk: the estimate from the recording off, where this code has it
FIXED = {"walk_from_recording": False} if "walk_from_recording" in AssociateOptions.__dataclass_fields__ else {}


def pair_f1(found, truths) -> list[float]:
    return [score_groups([[(fp.views[v].name, int(i)) for v, i in enumerate(m) if i >= 0]
                          for m in fp.result.members], t).pair_f1 for fp, t in zip(found, truths)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--alone", action="store_true", help="each frame also associated on its own")
    parser.add_argument("--exact", action="store_true", help="also on the truth's poses (the reference)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--walks", default=None,
                        help="instead: the recording at each of these walks (m; 0: every pair searched; auto: the "
                             "walk estimated from the recording, the default)")
    args = parser.parse_args(argv)
    run = lend_poses(load_run(args.out), args.dataset, args.frames, "frame0000.png")
    exact_images = {im.name: im for im in pycolmap.Reconstruction(str(args.dataset / "ground_truth")).images.values()}
    exact = RunModel({n: exact_images[n] for n in run.images}, run.bands, run.known, run.world, run.centre_sigma_m)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in run.images.items()}
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        truths, points = [], {}
        for k in range(args.frames):
            heads = {n: v for n, v in visible_heads(args.dataset, f"frame{k:04d}").items() if n in sizes}
            truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed + 1000 * k)
            truths.append(truth)
            points.update(truth.points)
        detections = from_arrays(points)
        configs = [("run", run, False, "auto"), ("run", run, True, "auto")] + (
            [("exact", exact, True, "auto")] if args.exact else [])
        if args.walks:
            configs = [("run", run, True, walk) for walk in args.walks.split(",")]
        for poses, model, revisit, walk in configs:
            options = AssociateOptions(pixel_sigma=1.5, revisit=revisit)
            if walk != "auto":
                options = dataclasses.replace(options, walk_m=float(walk) or None, **FIXED)
            cpu = time.process_time()
            found = associate_frames(model, detections, options)
            cpu = time.process_time() - cpu
            f1 = pair_f1(found, truths)
            row = {"seed": seed, "poses": poses, "revisit": revisit, "walk": walk,
                   "walk_m": [getattr(fp.result, "walk_m", None) for fp in found], "pair_f1": [round(x, 3) for x in f1],
                   "mean": round(float(np.mean(f1)), 3), "cpu_s": round(cpu, 1),
                   "corrected": [any(np.any(s) for s in fp.result.shift_px.values()) for fp in found]}
            rows.append(row)
            print(json.dumps(row), flush=True)
        if args.alone:
            alone = []
            for k, frame in enumerate(sorted(detections.frames())):
                one = from_arrays({n: xy for n, xy in points.items() if frame in n})
                fp = associate_frames(run, one, AssociateOptions(pixel_sigma=1.5))[0]
                alone.append((round(pair_f1([fp], [truths[k]])[0], 3),
                              any(np.any(s) for s in fp.result.shift_px.values())))
            row = {"seed": seed, "poses": "run", "alone": alone}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
