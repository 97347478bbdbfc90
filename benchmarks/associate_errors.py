"""Where the association's pairwise errors come from, against a rendered crowd's truth (one seed, frame 0).

    python benchmarks/associate_errors.py DATASET OUT [--seed 0] [--pixel-sigma 1.5] [--json errors.json]
    python benchmarks/associate_errors.py DATASET OUT --frames 4 [--seed 0]

``--frames N``: a recording (OUT a run of its first frame, whose poses the later frames take, as
benchmarks/associate_recording.py lends them): every frame associated as ``associate_frames`` carries them, and each
frame taken apart on the views, rates and appearance its own association used (its last ``_solve``, recorded):
the wrong and missed pairs by cause as above, the true groups by size (among the hypotheses, below the minimum score,
found exactly), why a true 2-view group was never a hypothesis (a member held by a person found again, which the
packing then did not keep as one person; a seed below the carried frames' floor), and what the detections held by
the persons found again ended in.

DATASET, OUT and the detections as in ``benchmarks/associate.py`` (the same seed gives the same detections).
Reports: the wrong pairs by cause (a false detection absorbed, two persons merged; the groups by size and kind), the
missed true pairs by cause (both detections left out, one left out, the person split between groups or absorbed
into another's) and by how many views detect the person, the persons found exactly / partly / not at all; then
whether the search or the model loses them: how many complete true groups are among the hypotheses, how the true
groups score, the packing's objective of the truth against the association's own, and the first packing again
with every true group added to its hypotheses (if that does not raise F1, the score, not the search, is the limit).

``--terms`` (frame 0): the score taken apart term by term (``score_terms``: the density prior, the height prior, the
point's volume, the members' detection probability, clutter density, normalisation and residuals, the views that see
the point without a member, the appearance and the head sizes; they sum to ``_Frame.score``): summed over the
association's groups and the truth's (those above the minimum score, as the packing's objective counts them); the
2-view groups (the truth's below and above the minimum, the association's right and wrong); each wrong 2-view group
against the true groups of its members' persons (what it displaced); and over every 2-view hypothesis above the
minimum, how well each term tells a right one (one person) from a wrong one: its area under the ROC curve and its
weight in a logistic regression on the terms (1 where a term is the log-likelihood ratio it claims to be).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np

import rigsfm.associate.solve as solve_module
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


TERMS = ("rho", "height", "volume", "detect", "clutter", "norm", "residual", "misses", "appearance", "size")


def score_terms(frame: _Frame, members: np.ndarray, points: np.ndarray, covariance: np.ndarray,
                ) -> dict[str, np.ndarray]:
    """``frame.score``'s terms per group (G each), and ``n_miss``: the views that see the point without a member. With
    the options' occlusion, ``detect`` is each member's view's own detection probability and ``misses`` each view
    without a member's ``log(1 - p_v)``."""
    o = frame.options
    occlusion = o.view_occlusion
    p_d = occlusion.q if occlusion is not None else o.detection_probability
    assert p_d is not None
    n = len(points)
    if o.height_prior is None:
        height = np.full(n, -math.log(o.heights[1] - o.heights[0]))
    else:
        mean, sigma = o.height_prior
        var = sigma ** 2 + np.maximum(covariance[:, 2, 2], 0.0)
        height = -0.5 * np.log(2 * math.pi * var) - 0.5 * (points[:, 2] - mean) ** 2 / var
    sign, logdet = np.linalg.slogdet(covariance)
    d2 = np.nan_to_num(frame.residuals(members, points), nan=0.0, posinf=1e6)
    present = members >= 0
    clutter = np.where(present, frame.clutter[np.where(present, members, 0)], 1.0)
    detect = present.sum(axis=1) * math.log(p_d)
    misses = np.zeros(n)
    frame._add_misses(misses, points, present)
    if occlusion is not None:  # the members' own probabilities against q, apart from the misses
        own = np.zeros(n)
        frame._add_misses(own, points, present, misses=False)
        detect, misses = detect + own, misses - own
    n_miss = np.zeros(n, np.int64)
    for v, view in enumerate(frame.views):
        uv, z = view.project(points)
        n_miss += view.inside(uv, z) & ~present[:, v]
    terms = {
        "rho": np.full(n, math.log(o.persons_per_m2)), "height": height,
        "volume": 1.5 * math.log(2 * math.pi) + 0.5 * np.where(sign > 0, logdet, -np.inf),
        "detect": detect,
        "clutter": -np.where(present, np.log(clutter), 0.0).sum(axis=1),
        "norm": -np.where(present, np.log(2 * math.pi * frame.noise ** 2)[None], 0.0).sum(axis=1),
        "residual": -0.5 * np.where(present, d2, 0.0).sum(axis=1), "misses": misses,
        "appearance": frame.appearance.group_log_ratio(frame.descriptors, members)
        if frame.appearance is not None and frame.descriptors is not None else np.zeros(n),
        "size": frame.size_log_ratio(members, points, covariance) if frame.log_radius is not None else np.zeros(n)}
    total = sum(terms[k] for k in TERMS)
    score = frame.score(members, points, covariance)
    finite = np.isfinite(score)
    assert np.allclose(total[finite], score[finite], atol=1e-6), "score_terms no longer sums to _Frame.score"
    terms["n_miss"] = n_miss
    return terms


def _kinds(pid: np.ndarray, members: np.ndarray, full: collections.Counter) -> np.ndarray:
    """Per group: 'complete' (one person, every detection of it), 'partial' (one person, not all) or 'wrong'."""
    out = []
    for row in members:
        ids = pid[row[row >= 0]]
        one = bool((ids >= 0).all() and len(set(ids.tolist())) == 1)
        out.append("wrong" if not one else "complete" if len(ids) == full[int(ids[0])] else "partial")
    return np.array(out)


def _auc(x: np.ndarray, positive: np.ndarray) -> float:
    from scipy.stats import rankdata

    r = rankdata(x)
    npos, nneg = int(positive.sum()), int((~positive).sum())
    return float((r[positive].sum() - npos * (npos + 1) / 2) / max(npos * nneg, 1))


def _logistic(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Logistic regression (Newton's method) of y on the columns of x and an intercept: weights and their sigmas."""
    a = np.c_[np.ones(len(x)), x]
    w = np.zeros(a.shape[1])
    hessian = np.eye(len(w))
    for _ in range(50):
        p = 1.0 / (1.0 + np.exp(-np.clip(a @ w, -30, 30)))
        hessian = (a * (p * (1 - p))[:, None]).T @ a + 1e-9 * np.eye(len(w))
        step = np.linalg.solve(hessian, a.T @ (y - p))
        w += step
        if np.abs(step).max() < 1e-9:
            break
    return w, np.sqrt(np.diag(np.linalg.inv(hessian)))


def terms_report(frame: _Frame, members: np.ndarray, true_m: np.ndarray, pid: np.ndarray, hyp: tuple) -> dict:
    """``--terms``: the score term by term on the association's groups, the truth's and the 2-view hypotheses."""
    full = collections.Counter(pid[pid >= 0].tolist())
    floor = frame.options.min_score
    sets = {}
    for name, m in (("association", members), ("truth", true_m)):
        p, c = frame.triangulate(m)
        p, c = frame.triangulate(m, p)
        sets[name] = (m, score_terms(frame, m, p, c), frame.score(m, p, c), _kinds(pid, m, full))
    columns = TERMS + ("n_miss",)
    report: dict = {"objective_by_term": {}, "two_view_groups": {}}
    for name, (m, t, s, _) in sets.items():
        size = np.minimum((m >= 0).sum(axis=1), 4)
        for sz in (2, 3, 4):
            above = (size == sz) & (s > floor)
            report["objective_by_term"][f"{name}, {sz}{'+' if sz == 4 else ''} views"] = {
                "groups": int(above.sum()), "at or below the minimum": int(((size == sz) & (s <= floor)).sum()),
                "minimum's offset": round(-floor * float(above.sum()), 1),
                **{k: round(float(t[k][above].sum()), 1) for k in TERMS}, "score": round(float(s[above].sum()), 1)}
    (tm, tt, ts, _), (am, at, as_, akind) = sets["truth"], sets["association"]
    t2, a2 = (tm >= 0).sum(axis=1) == 2, (am >= 0).sum(axis=1) == 2
    for label, t, s, sel in (("truth, at or below the minimum", tt, ts, t2 & (ts <= floor)),
                             ("truth, above the minimum", tt, ts, t2 & (ts > floor)),
                             ("association, right", at, as_, a2 & (akind != "wrong")),
                             ("association, wrong", at, as_, a2 & (akind == "wrong"))):
        report["two_view_groups"][label] = {"groups": int(sel.sum()),
                                            **{k: round(float(t[k][sel].mean()), 2) for k in columns},
                                            "score": round(float(s[sel].mean()), 2)}
    # each wrong 2-view group against the true group of each of its members' persons (seen in two views or more)
    owner = {int(pid[row[row >= 0][0]]): g for g, row in enumerate(tm)}
    diffs = []
    for g in np.flatnonzero(a2 & (akind == "wrong")).tolist():
        for p in pid[am[g][am[g] >= 0]].tolist():
            if p >= 0 and p in owner:
                h = owner[p]
                diffs.append([tt[k][h] - at[k][g] for k in columns] + [ts[h] - as_[g], int((tm[h] >= 0).sum())])
    d = np.array(diffs).reshape(-1, len(columns) + 2)
    report["displaced_true_minus_wrong"] = {
        label: {"pairs": int(sel.sum()), **{k: round(float(d[sel, i].mean()), 2) for i, k in enumerate(columns)},
                "score": round(float(d[sel, -2].mean()), 2),
                "true scores below the wrong": int((d[sel, -2] < 0).sum())}
        for label, sel in (("true group of 2 views", d[:, -1] == 2), ("true group of 3+ views", d[:, -1] >= 3))
        if sel.any()}
    # every 2-view hypothesis above the minimum: how each term tells right from wrong
    hm, hp, hc, hs = hyp
    keep = ((hm >= 0).sum(axis=1) == 2) & (hs > floor)
    hm, hp, hc, hs = hm[keep], hp[keep], hc[keep], hs[keep]
    t = score_terms(frame, hm, hp, hc)
    right = _kinds(pid, hm, full) != "wrong"
    varying = [k for k in TERMS if np.ptp(t[k]) > 0]
    w, sigma = _logistic(np.array([t[k] for k in varying]).T, right.astype(np.float64))
    report["two_view_hypotheses"] = {
        "count": int(len(hm)), "right": int(right.sum()),
        "auc": {**{k: round(_auc(t[k], right), 3) for k in varying + ["n_miss"]}, "score": round(_auc(hs, right), 3)},
        "logistic_weight": {k: f"{w[i + 1]:.2f} +- {sigma[i + 1]:.2f}" for i, k in enumerate(varying)}}
    return report


def analyse(dataset: Path, out: Path, seed: int, pixel_sigma: float, terms: bool = False) -> dict:
    options = AssociateOptions(pixel_sigma=pixel_sigma)
    model = load_run(out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(dataset, "frame0000").items() if n in sizes}
    truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed)
    found = associate_frames(model, from_arrays(truth.points), options)[0]
    views, result = found.views, found.result
    # a first frame grows every pair seed (associate_views: no seeds' floor)
    final = dataclasses.replace(options, detection_probability=result.detection_probability, occlusion=result.occlusion,
                                height_prior=result.height_prior, seed_min_score=None)
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
    if terms:
        report["terms"] = terms_report(frame, members, true_m, pid, frame.hypotheses())
    return report


def _pure(pid: np.ndarray, row: np.ndarray) -> bool:
    ids = pid[row[row >= 0]]
    return bool((ids >= 0).all() and len(set(ids.tolist())) == 1)


def analyse_frame(state: tuple, result, truth, options: AssociateOptions) -> dict:
    """One frame of a recording taken apart: ``state`` its association's last ``_solve`` (frame, members, ...)."""
    frame, members = state[0], state[1]
    views, offsets = frame.views, frame.offsets
    final = dataclasses.replace(options, detection_probability=result.detection_probability, occlusion=result.occlusion,
                                height_prior=result.height_prior)
    pid = np.concatenate([truth.person[v.name] for v in views])
    group_of = np.full(len(pid), -1)
    for g, row in enumerate(members):
        group_of[row[row >= 0]] = g
    report: dict = {"scores": _scores(views, members, offsets, truth)}
    wrong, kinds = collections.Counter(), collections.Counter()
    for row in members:
        ids = pid[row[row >= 0]]
        for a, b in itertools.combinations(ids.tolist(), 2):
            wrong["right" if a == b and a >= 0 else "a false detection" if min(a, b) < 0 else "two persons merged"] += 1
        kind = "pure" if _pure(pid, row) else "with a false detection" if len(set(ids[ids >= 0].tolist())) <= 1 \
            else "two or more persons"
        kinds[f"{min(len(ids), 4)}{'+' if len(ids) >= 4 else ''} views, {kind}"] += 1
    report["pairs_found"], report["groups"] = dict(wrong), dict(sorted(kinds.items()))
    persons = collections.defaultdict(list)
    for k, p in enumerate(pid.tolist()):
        if p >= 0:
            persons[p].append(k)
    missed, true_rows = collections.Counter(), []
    for p, dets in persons.items():
        if len(dets) < 2:
            continue
        gs = group_of[dets]
        for ga, gb in itertools.combinations(gs.tolist(), 2):
            if ga >= 0 and ga == gb:
                continue
            if ga < 0 and gb < 0:
                missed["both left out"] += 1
            elif ga < 0 or gb < 0:
                missed["one left out, the other in " + ("its own group" if _owner(pid, members[max(ga, gb)]) == p
                                                        else "another person's")] += 1
            else:
                own = _owner(pid, members[ga]) == p and _owner(pid, members[gb]) == p
                missed["split between its own groups" if own else "absorbed into another person's group"] += 1
        row = np.full(len(views), -1)
        row[frame.view_of[dets]] = dets
        true_rows.append(row)
    report["pairs_missed"] = dict(missed)
    true_m = np.array(true_rows)
    saved, frame.options = frame.options, final
    try:
        points, covariance = frame.triangulate(true_m)
        points, covariance = frame.triangulate(true_m, points)
        true_s = frame.score(true_m, points, covariance)
        grown = frame._grown.get(None)
        pool = set(map(tuple, grown[0].tolist())) if grown is not None else set()
        found = set(map(tuple, members.tolist()))
        size = np.minimum(np.sum(true_m >= 0, axis=1), 4)
        report["true_groups"] = {f"{s}{'+' if s == 4 else ''} views": {
            "count": int(sel.sum()), "among_hypotheses": int(sum(tuple(r) in pool for r in true_m[sel].tolist())),
            "below_min_score": int((true_s[sel] <= final.min_score).sum()),
            "found_exactly": int(sum(tuple(r) in found for r in true_m[sel].tolist()))}
            for s in (2, 3, 4) for sel in [size == s]}
        among = frame._among
        why = collections.Counter()
        for row in true_m[size == 2]:
            if tuple(row.tolist()) in pool:
                continue
            dets = row[row >= 0]
            if among is not None and not among[dets].all():
                why["a member held by a person found again"] += 1
            elif not len(frame._gated(row[None], None)[0]):
                why["outside the heights or a gate"] += 1
            elif among is not None and final.seed_min_score is not None \
                    and not len(frame._gated(row[None], final.seed_min_score)[0]):
                why["below the seeds' floor"] += 1
            else:
                why["grown into another group"] += 1
        report["true_2_view_groups_never_hypotheses"] = dict(why)
        if among is not None:
            held = np.flatnonzero(~among)
            ends = collections.Counter("left out" if group_of[d] < 0 else "in a right person"
                                       if _pure(pid, members[group_of[d]]) else "in a wrong person" for d in held)
            report["held_by_persons_found_again"] = {"held": len(held), **ends}
    finally:
        frame.options = saved
    return report


def analyse_recording(dataset: Path, out: Path, seed: int, pixel_sigma: float, frames: int) -> list[dict]:
    """Each frame of a recording associated as ``associate_frames`` carries them, taken apart (``analyse_frame``)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run as a script: the benchmarks package
    from benchmarks.associate import lend_poses

    options = AssociateOptions(pixel_sigma=pixel_sigma, poses_from="frame0000.png")
    model = lend_poses(load_run(out), dataset, frames, "frame0000.png")
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    truths, points = [], {}
    for k in range(frames):
        heads = {n: v for n, v in visible_heads(dataset, f"frame{k:04d}").items() if n in sizes}
        truths.append(make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed + 1000 * k))
        points.update(truths[-1].points)
    # the association's own state per frame: the last ``_solve`` of each ``associate_views`` call, recorded
    solves: list = []
    states: list = []
    solve_fn, views_fn = solve_module._solve, solve_module.associate_views

    def recorded_solve(*args, **kwargs):
        solves.append(solve_fn(*args, **kwargs))
        return solves[-1]

    def recorded_views(*args, **kwargs):
        solves.clear()
        result = views_fn(*args, **kwargs)
        states.append(solves[-1])
        return result

    import rigsfm.associate.pipeline as pipeline_module
    solve_module._solve, pipeline_module.associate_views = recorded_solve, recorded_views  # type: ignore[assignment]
    try:
        found = associate_frames(model, from_arrays(points), options)
    finally:
        solve_module._solve, pipeline_module.associate_views = solve_fn, views_fn  # type: ignore[assignment]
    if len(states) != len(found):
        raise SystemExit(f"{len(states)} associations for {len(found)} frames (a frame revisited): not taken apart")
    return [{"frame": fp.frame, "cpu_seconds": round(fp.cpu_seconds, 2), **analyse_frame(state, fp.result, truth, options)}
            for fp, state, truth in zip(found, states, truths)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--frames", type=int, default=1, help="a recording's first frames, each taken apart")
    parser.add_argument("--terms", action="store_true", help="frame 0's score taken apart term by term")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    report: dict | list = analyse(args.dataset, args.out, args.seed, args.pixel_sigma, args.terms) \
        if args.frames == 1 else \
        analyse_recording(args.dataset, args.out, args.seed, args.pixel_sigma, args.frames)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
