"""A walking crowd recorded at several frame rates: each frame's pair F1 at the options' default walk (``auto``:
0.15 m; the walk estimated from the recording was measured on a branch not kept) and with ``--walk`` fixed (0: every pair), on
the synthetic five-camera ring of tests/test_associate_tracked.py (exact truth, no rendering).

    python benchmarks/associate_walk.py [--fps 2,10] [--frames 4] [--heads 150] [--seeds 0,1] [--walks auto,0.15]

Each head walks at 1.3 +- 0.2 m/s (a fifth stand) on a heading that turns 20 degrees per second (1 sigma); the
cameras' pose errors are 2 px per axis, within the run's bands. benchmarks/README.md, "The walk from the recording",
has the numbers (measured, not landed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))  # the synthetic crowd of the tests

import numpy as np  # noqa: E402
from test_associate_tracked import OPTIONS, _pair_precision_recall, _recording  # noqa: E402

from rigsfm.associate import AssociateOptions, associate_frames  # noqa: E402

# a fixed walk: the estimate from the recording off, where this code has it
FIXED = {"walk_from_recording": False} if "walk_from_recording" in AssociateOptions.__dataclass_fields__ else {}


def walked_frames(fps: float, frames: int, heads: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    points = np.c_[rng.uniform(-4, 4, (heads, 2)), rng.uniform(1.6, 1.9, heads)]
    speed = np.where(rng.random(heads) < 0.2, 0.0, rng.normal(1.3, 0.2, heads))
    heading = rng.uniform(0, 2 * np.pi, heads)
    out = [points.copy()]
    for _ in range(frames - 1):
        heading += rng.normal(0, np.radians(20) / np.sqrt(fps), heads)
        points = points + np.c_[speed / fps * np.cos(heading), speed / fps * np.sin(heading), np.zeros(heads)]
        out.append(points.copy())
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fps", default="2,10")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--heads", type=int, default=150)
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--walks", default="auto,0.15", help="auto: the default; a number: --walk (0: every pair)")
    args = parser.parse_args(argv)
    for fps in (float(f) for f in args.fps.split(",")):
        for seed in (int(s) for s in args.seeds.split(",")):
            frames = walked_frames(fps, args.frames, args.heads, seed)
            shifts = np.random.default_rng(100 + seed).normal(0.0, 2.0, (5, 2))
            model, detections, ids = _recording(frames, shifts, sigma_px=3.5)
            for walk in args.walks.split(","):
                options = dataclasses.replace(OPTIONS, detection_probability=None)
                if walk != "auto":
                    options = dataclasses.replace(options, walk_m=float(walk) or None, **FIXED)
                cpu = time.process_time()
                found = associate_frames(model, detections, options)
                cpu = time.process_time() - cpu
                f1 = []
                for fp, truth in zip(found, ids):
                    p, r = _pair_precision_recall(fp.result.members, truth)
                    f1.append(round(2 * p * r / max(p + r, 1e-9), 3))
                used = [getattr(fp.result, "walk_m", None) for fp in found]
                print(json.dumps({"fps": fps, "seed": seed, "walk": walk, "pair_f1": f1,
                                  "mean_carried": round(float(np.mean(f1[1:])), 3), "walk_m": used,
                                  "cpu_s": round(cpu, 1)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
