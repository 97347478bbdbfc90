"""Where the association's pairwise errors come from, against a rendered crowd's truth (one seed, frame 0).

    python benchmarks/associate_errors.py DATASET OUT [--seed 0] [--pixel-sigma 1.5] [--json errors.json]

DATASET, OUT and the detections as in ``benchmarks/associate.py`` (the same seed gives the same detections).
Reports: the wrong pairs by cause (a false detection absorbed, two persons merged; the groups by size and kind), the
missed true pairs by cause (both detections left out, one left out, the person split between groups or absorbed
into another's) and by how many views detect the person, the persons found exactly / partly / not at all; then
whether the search or the model loses them: how many complete true groups are among the hypotheses, how the true
groups score, the packing's objective of the truth against the association's own, and the first packing again
with every true group added to its hypotheses (if that does not raise F1, the score, not the search, is the limit).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads
from rigsfm.associate.frame import _Frame
from rigsfm.associate.packing import _pack


def _scores(views, members: np.ndarray, offsets: np.ndarray, truth) -> dict:
    groups = [[(views[v].name, int(i - offsets[v])) for v, i in enumerate(m) if i >= 0] for m in members]
    s = score_groups(groups, truth)
    return {"pair_precision": round(s.pair_precision, 3), "pair_recall": round(s.pair_recall, 3),
            "pair_f1": round(s.pair_f1, 3), "person_f1": round(s.person_f1, 3)}


def _owner(pid: np.ndarray, row: np.ndarray) -> int:
    return collections.Counter(pid[row[row >= 0]].tolist()).most_common(1)[0][0]


def analyse(dataset: Path, out: Path, seed: int, pixel_sigma: float) -> dict:
    options = AssociateOptions(pixel_sigma=pixel_sigma)
    model = load_run(out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(dataset, "frame0000").items() if n in sizes}
    truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed)
    found = associate_frames(model, from_arrays(truth.points), options)[0]
    views, result = found.views, found.result
    final = dataclasses.replace(options, detection_probability=result.detection_probability,
                                height_prior=result.height_prior)
    frame = _Frame(views, final, result.appearance)  # the final association's views, rates and appearance
    offsets = frame.offsets
    pid = np.concatenate([truth.person[v.name] for v in views])  # true person per stacked detection, -1 false
    members = np.where(result.members >= 0, result.members + offsets[:-1][None], -1)
    group_of = np.full(len(pid), -1)
    for g, row in enumerate(members):
        group_of[row[row >= 0]] = g
    report: dict = {"scores": _scores(views, members, offsets, truth)}

    wrong = collections.Counter()
    kinds = collections.Counter()
    for row in members:
        ids = pid[row[row >= 0]]
        for a, b in itertools.combinations(ids.tolist(), 2):
            wrong["right" if a == b and a >= 0 else "a false detection" if min(a, b) < 0 else "two persons merged"] += 1
        real = set(ids[ids >= 0].tolist())
        kind = "pure" if (ids >= 0).all() and len(real) == 1 else \
            "with a false detection" if len(real) <= 1 else "two or more persons"
        kinds[f"{min(len(ids), 6)} views, {kind}"] += 1
    report["pairs_found"] = dict(wrong)
    report["groups"] = dict(sorted(kinds.items()))

    persons = collections.defaultdict(list)
    for k, p in enumerate(pid.tolist()):
        if p >= 0:
            persons[p].append(k)
    missed, by_views, status = collections.Counter(), collections.Counter(), collections.Counter()
    true_rows = []
    for p, dets in persons.items():
        n = len(dets)
        if n < 2:
            continue
        key = f"{min(n, 6)}{'+' if n >= 6 else ''} views"
        by_views[key + ", true pairs"] += n * (n - 1) // 2
        gs = group_of[dets]
        for ga, gb in itertools.combinations(gs.tolist(), 2):
            if ga >= 0 and ga == gb:
                continue
            by_views[key + ", missed"] += 1
            if ga < 0 and gb < 0:
                missed["both left out"] += 1
            elif ga < 0 or gb < 0:
                g = max(ga, gb)
                missed["one left out, the other in " + ("its own group" if _owner(pid, members[g]) == p
                                                        else "another person's")] += 1
            else:
                own = _owner(pid, members[ga]) == p and _owner(pid, members[gb]) == p
                missed["split between its own groups" if own else "absorbed into another person's group"] += 1
        exact = len(set(gs.tolist())) == 1 and gs[0] >= 0 and (pid[members[gs[0]][members[gs[0]] >= 0]] == p).all()
        status[f"{key}: " + ("exact" if exact else "not found" if (gs < 0).all() else "partly or mixed")] += 1
        row = np.full(len(views), -1)
        row[frame.view_of[dets]] = dets
        true_rows.append(row)
    report["pairs_missed"] = dict(missed)
    report["pairs_by_views"] = dict(sorted(by_views.items()))
    report["persons"] = dict(sorted(status.items()))

    true_m = np.array(true_rows)
    points, covariance = frame.triangulate(true_m)
    points, covariance = frame.triangulate(true_m, points)
    true_s = frame.score(true_m, points, covariance)
    hyp_m, _, _, hyp_s = frame.hypotheses()
    pool = set(map(tuple, hyp_m.tolist()))
    size = np.sum(true_m >= 0, axis=1)
    report["true_groups"] = {
        f"{s}{'+' if s == 6 else ''} views": {
            "count": int(sel.sum()), "score_median": round(float(np.median(true_s[sel])), 2),
            "below_min_score": int((true_s[sel] <= final.min_score).sum()),
            "among_hypotheses": int(sum(tuple(r) in pool for r in true_m[sel].tolist()))}
        for s in range(2, 7) for sel in [size == s if s < 6 else size >= 6] if sel.any()}
    points, covariance = frame.triangulate(members)
    points, covariance = frame.triangulate(members, points)
    own_s = frame.score(members, points, covariance)
    report["objective"] = {"association": round(float(np.sum(np.maximum(own_s - final.min_score, 0))), 1),
                           "truth": round(float(np.sum(np.maximum(true_s - final.min_score, 0))), 1)}
    total = int(offsets[-1])
    for label, m, s in (("first_packing", hyp_m, hyp_s),
                        ("first_packing_with_true_groups", np.concatenate([hyp_m, true_m]),
                         np.concatenate([hyp_s, true_s]))):
        keep = s > final.min_score
        chosen = _pack(m[keep], s[keep] - final.min_score, total, final.time_limit_s)
        report[label] = _scores(views, m[keep][chosen], offsets, truth)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    report = analyse(args.dataset, args.out, args.seed, args.pixel_sigma)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
