"""CPU time of ``rigsfm associate`` per frame: one frame that self-calibrates, then frames that carry its shifts.

    python benchmarks/associate_speed.py DATASET OUT [--seeds 2] [--carried 2] [--dump DIR]

DATASET, OUT: as for benchmarks/associate.py (a crowd rendered with persons, and ``rigsfm run`` on it). Frame 0's
detections are benchmarks/associate.py's (its true visible heads, 1.5 px noise, 10 % missed, 5 % false, per seed);
each carried frame k is the same heads with other noise, misses and false detections (seed + 1000 k), associated
as the next frame of the same static cameras is by ``associate_frames`` (the shifts, bands, head sizes, rates and
appearance model of the frame before carried). A rendered scene of one frame is enough. Prints, per seed and frame, this process's CPU seconds,
the wall seconds and the pair F1 against the truth; ``--dump`` writes each seed's persons (members, points,
covariances, scores) and views' shifts to DIR/seed<S>.npz, to compare two versions of the code exactly.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from rigsfm.associate import AssociateOptions, from_arrays, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads
from rigsfm.associate.pipeline import frame_views
from rigsfm.associate.solve import associate_views


def static_frames(dataset: Path, out: Path, seed: int, carried: int):
    """Frame 0's visible heads as ``carried`` + 1 frames of a static crowd, each with its own noise, misses and
    false detections: per frame (k, its truth, its views, each carrying the frame before's camera view as
    associate_frames does, its detections). The views are associated by the caller before the next is made."""
    model = load_run(out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(dataset, "frame0000").items() if n in sizes}
    views = None
    for k in range(carried + 1):
        truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed + 1000 * k)
        detections = from_arrays(truth.points)
        new = frame_views(model, detections, "frame0000", sorted(detections.images))
        if views is not None:
            for view, before in zip(new, views):
                view.carry(before)
        views = new
        yield k, truth, views, detections


def run_seed(dataset: Path, out: Path, seed: int, carried: int, options: AssociateOptions) -> tuple[list, dict]:
    rows, arrays, earlier = [], {}, None
    for k, truth, views, _ in static_frames(dataset, out, seed, carried):
        wall, cpu = time.perf_counter(), time.process_time()
        result = associate_views(views, options, carried=k > 0, earlier=earlier)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        earlier = result
        groups = [[(views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in result.members]
        scores = score_groups(groups, truth)
        rows.append({"seed": seed, "frame": k, "carried": k > 0, "cpu_seconds": round(cpu, 2),
                     "seconds": round(wall, 2), "persons": len(result), "pair_f1": round(scores.pair_f1, 4),
                     "person_f1": round(scores.person_f1, 4)})
        print(json.dumps(rows[-1]), flush=True)
        arrays.update({f"members{k}": result.members, f"points{k}": result.points,
                       f"covariances{k}": result.covariances, f"scores{k}": result.scores,
                       f"shifts{k}": np.array([v.shift_px for v in views])})
    return rows, arrays


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--carried", type=int, default=2, help="frames after the first, carrying its shifts")
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--dump", type=Path, default=None, help="folder for each seed's persons (npz)")
    args = parser.parse_args(argv)
    options = AssociateOptions(pixel_sigma=args.pixel_sigma)
    for seed in range(args.seeds):
        _, arrays = run_seed(args.dataset, args.out, seed, args.carried, options)
        if args.dump is not None:
            args.dump.mkdir(parents=True, exist_ok=True)
            np.savez(args.dump / f"seed{seed}.npz", **arrays)
    return 0


if __name__ == "__main__":
    sys.exit(main())
