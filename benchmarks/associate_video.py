"""Association over several frames of a recording: how much a hypothesis' evidence summed over frames separates
the right groups from chance ones (an oracle first, then a truth-free per-view linking).

    python benchmarks/associate_video.py DATASET OUT [--frames 6] [--seeds 2] [--link truth|nearest] [--json F]

DATASET: a crowd rendered with persons over several frames (``python -m rigsfm.synth --frames-per-rig T
--frame-period-s 0.1``); OUT: ``rigsfm run`` on the same cameras (static rigs: its frame-0 poses are every frame's,
so a run of the scene's first frame serves: each later frame's images take their camera's frame-0 pose, band and
centre covariance, and the greys come from DATASET/images). Detections per frame as benchmarks/associate.py makes
them (true visible heads, 1.5 px noise, 10 % missed, 5 % false; seed + 1000 k for frame k).

Every frame is associated by ``associate_frames`` as it is (frame 0 self-calibrates, the rest carry its shifts).
Then frame 0's hypotheses (its final association's grown groups) are followed through the later frames: each member
detection is linked to a detection of the same view in the next frame, by the truth's person ids (``--link truth``,
an oracle) or by mutual nearest neighbours within the distance a walker's head can move in one frame period
(``--link nearest``, no truth), and the linked group is triangulated again in that frame. A frame's evidence is the
log-likelihood ratio of its squared residuals between "one person" (chi-square at the pixel noise) and "two persons
walking independently" (the same residuals spread by the heads' motion in a frame, ``--motion-px``), floored. Reported
per T (frames summed): ROC AUC of right against wrong 2-view and 3-view hypotheses, one frame's score against the
summed one, and pair F1 of the first packing of frame 0 with either score.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from pathlib import Path

import numpy as np
import scipy.stats

import rigsfm.associate.solve as solve
from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads
from rigsfm.associate.pipeline import RunModel
from rigsfm.core.names import ImageName


class _Posed:
    """A later frame's image of a static camera: its frame-0 image's camera and pose under the later name."""

    def __init__(self, name: str, image) -> None:
        self.name, self.has_pose, self._image = name, True, image  # the image holds its camera alive
        self.camera = image.camera
        self._pose, self._centre = image.cam_from_world(), image.projection_center()

    def cam_from_world(self):
        return self._pose

    def projection_center(self):
        return self._centre


def video_model(model: RunModel, dataset: Path, frames: int) -> RunModel:
    """``model`` (a run of frame 0) with every later frame's narrow images posed as their camera's frame 0."""
    images, bands, sigma, cov = {}, {}, {}, {}
    camera_of = {ImageName.parse(n).camera: n for n in model.images}
    renamed: dict[str, dict[str, str]] = {}
    for k in range(frames):
        for camera, name in camera_of.items():
            new = name.replace("frame0000", f"frame{k:04d}")
            images[new] = _Posed(new, model.images[name])
            renamed.setdefault(name, {})[f"{k}"] = new
            if name in model.centre_sigma_m:
                sigma[new] = model.centre_sigma_m[name]
            if name in model.centre_covariance_m2:
                cov[new] = model.centre_covariance_m2[name]
    for (a, b), band in model.bands.items():
        for k in range(frames):
            bands[(renamed[a][f"{k}"], renamed[b][f"{k}"])] = band
    return RunModel(images, bands, set(images), model.world, sigma, cov, Path(dataset) / "images", {})


def auc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney): the chance that a right group outscores a wrong one."""
    pos, neg = int(label.sum()), int((~label).sum())
    if not pos or not neg:
        return float("nan")
    ranks = scipy.stats.rankdata(score)
    return float((ranks[label].sum() - pos * (pos + 1) / 2) / (pos * neg))


def link_truth(frame_a, frame_b, person_a: np.ndarray, person_b: np.ndarray) -> np.ndarray:
    """Per detection of ``frame_a`` (stacked), the detection of the same view and true person in ``frame_b``."""
    out = np.full(len(person_a), -1, dtype=np.int64)
    for v in range(len(frame_a.views)):
        a = np.arange(frame_a.offsets[v], frame_a.offsets[v + 1])
        b = np.arange(frame_b.offsets[v], frame_b.offsets[v + 1])
        where = {int(p): int(i) for i, p in zip(b, person_b[b]) if p >= 0}
        out[a] = [where.get(int(p), -1) if p >= 0 else -1 for p in person_a[a]]
    return out


def link_nearest(frame_a, frame_b, radius: np.ndarray) -> np.ndarray:
    """Per detection of ``frame_a``, its mutual nearest detection of the same view in ``frame_b`` within the view's
    ``radius`` (px), else -1."""
    from scipy.spatial import cKDTree

    out = np.full(int(frame_a.offsets[-1]), -1, dtype=np.int64)
    for v in range(len(frame_a.views)):
        a = np.arange(frame_a.offsets[v], frame_a.offsets[v + 1])
        b = np.arange(frame_b.offsets[v], frame_b.offsets[v + 1])
        if not len(a) or not len(b):
            continue
        ua, ub = frame_a.uv[a], frame_b.uv[b]
        da, ia = cKDTree(ub).query(ua)
        _, ib = cKDTree(ua).query(ub)
        mutual = (ib[ia] == np.arange(len(a))) & (da <= radius[v])
        out[a[mutual]] = b[ia[mutual]]
    return out


def continue_groups(frame, members: np.ndarray, last_uv: np.ndarray, reach: np.ndarray, motion_px: float,
                    floor: float, candidates: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each group's best continuation in ``frame``: per member view, up to ``candidates`` detections within its
    ``reach`` (px) of where it was last seen (``last_uv``, G x V x 2; NaN: not in the group), every combination's
    evidence (frame_evidence), the best one less log(its number of combinations), as a search over c combinations
    finds a chance agreement c times as often. Groups of four or more views try the nearest detection only.
    Returns the evidence, whether tested, and the chosen members (G x V, -1 where none)."""
    from scipy.spatial import cKDTree

    g, nv = members.shape
    cand = np.full((g, nv, candidates), -1, dtype=np.int64)
    for v in range(nv):
        rows = np.flatnonzero(members[:, v] >= 0)
        lo, hi = frame.offsets[v], frame.offsets[v + 1]
        if not len(rows) or hi == lo:
            continue
        tree = cKDTree(frame.uv[lo:hi])
        d, i = tree.query(last_uv[rows, v], k=min(candidates, hi - lo))
        d, i = d.reshape(len(rows), -1), i.reshape(len(rows), -1)
        ok = d <= reach[rows, v][:, None]
        cand[rows[:, None], v, np.arange(d.shape[1])[None]] = np.where(ok, i + lo, -1)
    size = np.sum(members >= 0, axis=1)
    evidence = np.zeros(g)
    tested = np.zeros(g, dtype=bool)
    chosen = np.full((g, nv), -1, dtype=np.int64)
    for n in np.unique(size):
        rows = np.flatnonzero(size == n)
        c = candidates if n <= 3 else 1
        views = np.argsort(members[rows] < 0, axis=1, kind="stable")[:, :n]  # the member views, in order
        combos = np.array(list(itertools.product(range(c), repeat=int(n))))  # K x n
        trial = np.full((len(rows), len(combos), nv), -1, dtype=np.int64)
        for slot in range(int(n)):
            v = views[:, slot]
            trial[np.arange(len(rows))[:, None], np.arange(len(combos))[None], v[:, None]] = \
                cand[rows[:, None], v[:, None], combos[None, :, slot]]
        # a combination counts where each of its slots holds a candidate or the view has none at all
        flat = trial.reshape(-1, nv)
        value, ok = frame_evidence(frame, flat, motion_px, floor)
        value, ok = value.reshape(len(rows), -1), ok.reshape(len(rows), -1)
        distinct = np.array([len({tuple(r) for r in t[o]}) for t, o in zip(trial, ok)])
        value = np.where(ok, value, -np.inf)
        best = np.argmax(value, axis=1)
        has = ok.any(axis=1)
        evidence[rows[has]] = value[has, best[has]] - np.log(np.maximum(distinct[has], 1))
        tested[rows[has]] = True
        chosen[rows[has]] = trial[np.flatnonzero(has), best[has]]
    return evidence, tested, chosen


def frame_evidence(frame, members: np.ndarray, motion_px: float, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Per group (members in ``frame``; -1: none), the log-likelihood ratio of its residuals, one person against two
    independent walkers, and whether it had two or more members to test (else 0)."""
    n = np.sum(members >= 0, axis=1)
    out = np.zeros(len(members))
    tested = n >= 2
    if not tested.any():
        return out, tested
    m = members[tested]
    points, covariance = frame.triangulate(m)
    points, covariance = frame.triangulate(m, points)
    d2 = np.nan_to_num(frame.residuals(m, points), nan=0.0, posinf=1e6)
    lam = 1.0 + (motion_px / frame.noise[None]) ** 2  # per view, the two-walker residuals' spread over the noise
    present = m >= 0
    per = np.where(present, -0.5 * d2 * (1.0 - 1.0 / lam) + 0.5 * np.log(lam), 0.0)
    # 2n - 3 degrees of freedom: the three coordinates of the point are fitted, so take off the mean of three
    dof = 2 * np.sum(present, axis=1) - 3
    value = np.sum(per, axis=1) * dof / np.maximum(2 * np.sum(present, axis=1), 1)
    lo, hi = frame.options.heights
    value = np.where((points[:, 2] >= lo) & (points[:, 2] <= hi), value, floor)
    out[tested] = np.maximum(value, floor)
    return out, tested


def run_seed(dataset: Path, out: Path, seed: int, frames: int, link: str, motion_px: float, floor: float,
             radius_px: float, options: AssociateOptions, speed_m_s: float = 1.3, period_s: float = 0.1) -> dict:
    model = video_model(load_run(out), dataset, frames)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    truths, points = [], {}
    for k in range(frames):
        heads = {n: v for n, v in visible_heads(dataset, f"frame{k:04d}").items() if n in sizes}
        truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed + 1000 * k)
        truths.append(truth)
        points.update(truth.points)
    captured: list = []
    original = solve._solve

    def capturing(*args, **kwargs):
        state = original(*args, **kwargs)
        captured.append(state[0])
        return state

    solve._solve = capturing
    try:
        found = associate_frames(model, from_arrays(points), options)
    finally:
        solve._solve = original
    # each frame's final association is the last _solve before the next frame's first: match by views
    finals = []
    for fp in found:
        names = [v.name for v in fp.views]
        finals.append([f for f in captured if [v.name for v in f.views] == names][-1])
    person = [np.concatenate([truth.person[v.name] for v in f.views]) for f, truth in zip(finals, truths)]
    single_f1 = [score_groups([[(fp.views[v].name, int(i)) for v, i in enumerate(m) if i >= 0]
                               for m in fp.result.members], t).pair_f1 for fp, t in zip(found, truths)]
    f0 = finals[0]
    members, pts, cov = f0._grown[None]
    score0 = f0.score(members, pts, cov)
    ids = np.where(members >= 0, person[0][np.maximum(members, 0)], -2)
    size = np.sum(members >= 0, axis=1)
    first = np.max(np.where(members >= 0, ids, -3), axis=1)
    right = np.all((members < 0) | (ids == first[:, None]), axis=1) & (first >= 0)
    rows = []
    # each member's latest linked detection and its frame: a member missed in a frame is looked for again in the
    # next one from where it was last seen (the truth links frame 0 to frame k directly)
    last = members.copy()
    last_frame = np.zeros(members.shape, dtype=np.int64)
    last_uv = np.where((members >= 0)[..., None], f0.uv[np.maximum(members, 0)], np.nan)
    depth = np.stack([v.project(pts)[1] for v in f0.views], axis=1)  # G x V, the point's depth in each view
    focal = np.array([v.focal for v in f0.views])
    summed = score0.copy()
    tested_frames = np.zeros(len(members), dtype=np.int64)
    links: dict[tuple[int, int], np.ndarray] = {}
    for k in range(frames):
        if k > 0 and link == "search":
            gap = k - last_frame
            reach = speed_m_s * period_s * gap * focal[None] / np.maximum(depth, 1.0) + 3 * finals[k].noise[None]
            evidence, tested, current = continue_groups(finals[k], members, last_uv, reach, motion_px, floor)
            found_now = current >= 0
            last_uv = np.where(found_now[..., None], finals[k].uv[np.maximum(current, 0)], last_uv)
            last_frame = np.where(found_now, k, last_frame)
            summed = summed + evidence
            tested_frames += tested
        elif k > 0:
            current = np.full(members.shape, -1, dtype=np.int64)
            for j in np.unique(last_frame[last >= 0]):
                if (j, k) not in links:
                    if link == "truth":
                        links[(j, k)] = link_truth(finals[j], finals[k], person[j], person[k])
                    else:
                        links[(j, k)] = link_nearest(finals[j], finals[k], np.full(len(finals[k].views),
                                                                                    radius_px * (k - j)))
                here = (last >= 0) & (last_frame == j)
                current[here] = links[(j, k)][last[here]]
            found_now = current >= 0
            last = np.where(found_now, current, last)
            last_frame = np.where(found_now, k, last_frame)
            evidence, tested = frame_evidence(finals[k], current, motion_px, floor)
            summed = summed + evidence
            tested_frames += tested
        row = {"seed": seed, "frames": k + 1, "link": link, "single_f1_frame": round(single_f1[k], 4)}
        for n_views in (2, 3):
            sel = (size == n_views) & np.isfinite(score0)
            row[f"auc{n_views}_one"] = round(auc(score0[sel], right[sel]), 4)
            row[f"auc{n_views}_summed"] = round(auc(summed[sel], right[sel]), 4)
            row[f"right{n_views}"] = int(right[sel].sum())
            row[f"wrong{n_views}"] = int((~right[sel]).sum())
        total = int(f0.offsets[-1])
        for name, value in (("one", score0), ("summed", summed)):
            ok = value > options.min_score
            chosen = solve._pack(members[ok], value[ok] - options.min_score, total, options.time_limit_s)
            kept = members[ok][chosen]
            groups = [[(f0.views[v].name, int(i - f0.offsets[v])) for v, i in enumerate(m) if i >= 0] for m in kept]
            s = score_groups(groups, truths[0])
            row[f"f1_{name}"] = round(s.pair_f1, 4)
            row[f"p_{name}"] = round(s.pair_precision, 4)
            row[f"r_{name}"] = round(s.pair_recall, 4)
        row["tested_right_frames"] = round(float(np.mean(tested_frames[right])), 2)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return {"rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--link", choices=("truth", "nearest", "search"), default="truth")
    parser.add_argument("--motion-px", type=float, default=8.0, help="a head's typical motion in a frame (px)")
    parser.add_argument("--radius-px", type=float, default=16.0,
                        help="nearest linking: a head's farthest move in a frame (px)")
    parser.add_argument("--period-s", type=float, default=0.1, help="the recording's frame period (s)")
    parser.add_argument("--floor", type=float, default=-8.0, help="one frame's evidence at least this")
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    options = AssociateOptions(pixel_sigma=args.pixel_sigma)
    out = [run_seed(args.dataset, args.out, s, args.frames, args.link, args.motion_px, args.floor, args.radius_px,
                    options, period_s=args.period_s)
           for s in range(args.seeds)]
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
