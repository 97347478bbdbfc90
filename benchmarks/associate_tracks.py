"""Persons linked across a recording's frames (``rigsfm.associate.trajectories``) against the truth: the walk it
estimates, how often a link is right against the confidence it gives, and how many tracks go on rightly.

    python benchmarks/associate_tracks.py [--fps 2,5,10] [--frames 4] [--heads 150,300] [--seeds 0,1]
    python benchmarks/associate_tracks.py --rendered DATASET OUT [--frames 4] [--poses-from FRAME] [--seeds 0,1]

The walking crowd of benchmarks/associate_walk.py (the synthetic five-camera ring of tests/test_associate_tracked.py:
exact truth, no rendering; each head walks 1.3 +- 0.2 m/s, a fifth standing, on a heading that turns 20 degrees per
second), every frame associated as ``rigsfm associate`` does (``associate_frames``). A person is a head where most of
its detections are that head's. Per frame after the first: the walk per floor axis estimated and the truth's (the
heads' own displacement), the persons linked, the share of links right among those between two persons who are heads
(against their mean confidence), the share of the persons found in both frames linked rightly, and the tracks that
go on (links above the tracks' confidence): how many and how many rightly (a link to or from a person who is no head
counts as wrong there), and those between two persons who are heads with their mean confidence.

``--rendered DATASET OUT``: a rendered recording of persons (DATASET) and a run of it (OUT; ``--poses-from`` its frame
whose poses the later frames take), detections as benchmarks/associate.py makes them (its ``evaluate``), the truth's
walk from the rendered heads' own centres.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))  # the synthetic crowd of the tests
sys.path.insert(0, str(REPO / "benchmarks"))

import numpy as np  # noqa: E402
from associate_walk import walked_frames  # noqa: E402
from test_associate_tracked import OPTIONS, _recording  # noqa: E402

from rigsfm.associate import associate_frames  # noqa: E402
from rigsfm.associate.trajectories import TRACK_CONFIDENCE, tracks  # noqa: E402


def heads_of(members: np.ndarray, truth: list[np.ndarray]) -> np.ndarray:
    """Per person, the head most of its detections are (-1: none holds a majority, or a false detection)."""
    out = []
    for row in members:
        held = collections.Counter(int(truth[v][i]) for v, i in enumerate(row) if i >= 0).most_common(1)[0]
        out.append(held[0] if 2 * held[1] > int(np.sum(row >= 0)) else -1)
    return np.array(out, dtype=np.int64)


def score(found, ids: list[list[np.ndarray]], frames: list[np.ndarray]) -> list[dict]:
    """Per frame after the first, its links against the truth: ``ids`` per frame and view each detection's head,
    ``frames`` per frame every head's true centre (the same head in the same row)."""
    ids_list, links = tracks([(f.result.points, f.result.covariances) for f in found])
    rows = []
    for k in range(1, len(found)):
        a, b = heads_of(found[k - 1].result.members, ids[k - 1]), heads_of(found[k].result.members, ids[k])
        link = links[k]
        assert link is not None  # every frame after the first has its links
        e = link.earlier
        linked = e >= 0
        before = a[np.maximum(e, 0)]
        valid = linked & (b >= 0) & (before >= 0)
        right = valid & (before == b)
        both = len(set(a[a >= 0].tolist()) & set(b[b >= 0].tolist()))
        goes_on = linked & (np.nan_to_num(link.confidence) > TRACK_CONFIDENCE)
        true_walk = float(np.sqrt(np.mean((frames[k][:, :2] - frames[k - 1][:, :2]) ** 2)))
        rows.append({"frame": k, "persons": len(b), "walk_m": round(link.walk_m or float("nan"), 3),
                     "true_walk_m": round(true_walk, 3), "linked": int(linked.sum()),
                     "right_share": round(float(right.sum() / max(valid.sum(), 1)), 3),
                     "confidence": round(float(np.mean(link.confidence[valid])) if valid.any() else float("nan"), 3),
                     "found_in_both": both, "linked_rightly": round(float(right.sum() / max(both, 1)), 3),
                     "tracks_on": int(goes_on.sum()), "tracks_on_rightly": int((goes_on & right).sum()),
                     # the tracks that go on between two persons who are heads: how often rightly, how sure
                     "tracks_on_heads": int((goes_on & valid).sum()),
                     "tracks_on_heads_confidence": round(float(np.mean(link.confidence[goes_on & valid]))
                                                         if (goes_on & valid).any() else float("nan"), 3)})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fps", default="2,5,10")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--heads", default="150,300")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--rendered", nargs=2, type=Path, metavar=("DATASET", "OUT"))
    parser.add_argument("--poses-from", default=None)
    args = parser.parse_args(argv)
    if args.rendered:
        from associate import evaluate

        from rigsfm.associate import AssociateOptions
        from rigsfm.associate.evaluate import true_heads

        dataset, out = args.rendered
        truth_frames = [true_heads(dataset, k) for k in range(args.frames)]
        for seed in (int(s) for s in args.seeds.split(",")):
            result = evaluate(dataset, out, seed, AssociateOptions(poses_from=args.poses_from), args.frames)
            found = result["found"]
            ids = [[truth.person[view.name] for view in frame.views] for frame, truth in zip(found, result["truths"])]
            print(json.dumps({"dataset": str(dataset), "seed": seed, "frames": score(found, ids, truth_frames),
                              "pair_f1": [round(f["scores"]["pair_f1"], 3) for f in result["frames"]]}), flush=True)
        return 0
    for heads in (int(h) for h in args.heads.split(",")):
        for fps in (float(f) for f in args.fps.split(",")):
            for seed in (int(s) for s in args.seeds.split(",")):
                frames = walked_frames(fps, args.frames, heads, seed)
                shifts = np.random.default_rng(100 + seed).normal(0.0, 2.0, (5, 2))
                model, detections, ids = _recording(frames, shifts, sigma_px=3.5)
                found = associate_frames(model, detections, dataclasses.replace(OPTIONS, detection_probability=None))
                cpu = time.process_time()
                rows = score(found, ids, frames)
                cpu = time.process_time() - cpu
                print(json.dumps({"heads": heads, "fps": fps, "seed": seed, "frames": rows,
                                  "cpu_s_links_and_scoring": round(cpu, 3)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
