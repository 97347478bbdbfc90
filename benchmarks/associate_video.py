"""Association over several frames of a recording: how much a hypothesis' evidence summed over frames separates
the right groups from chance ones (an oracle first, then truth-free per-view links). Measurement only.

    python benchmarks/associate_video.py DATASET OUT [--frames 6] [--seeds 2] [--link truth,nearest,walk,search]
        [--motion off,on] [--robust] [--floor -8] [--json F]

DATASET: a crowd rendered with persons over several frames (``python -m rigsfm.synth --frames-per-rig T
--frame-period-s 0.1``); OUT: ``rigsfm run`` on the same cameras (static rigs: its frame-0 poses are every frame's,
so a run of the scene's first frame serves: each later frame's images take their camera's frame-0 pose, band and
centre covariance, and the greys come from DATASET/images). Detections per frame as benchmarks/associate.py makes
them (true visible heads, 1.5 px noise, 10 % missed, 5 % false; seed + 1000 k for frame k).

Every frame is associated once by ``associate_frames`` as it is (frame 0 self-calibrates, the rest carry its shifts).
Then frame 0's hypotheses (its final association's grown groups) are followed through the later frames, once per
(link, motion) configuration: each member detection is linked to a detection of its view in a later frame (a member
missed in a frame is looked for again from where it was last seen) and the linked group is triangulated again
there. Links: ``truth`` (the person ids: an oracle), ``nearest`` (mutual nearest within ``--radius-px`` a frame),
``walk`` (nearest one to one under a walk's image metric, the head at the crowd's mean height), ``search`` (per
member up to three detections within a walker's reach, the best combination less log of the combinations). A frame's
evidence is the log-likelihood ratio of the group's squared residuals between "one person" (chi-square at the
view's noise) and "two persons walking independently" (the residuals spread by ``--motion-px`` times the frames
since frame 0), floored at ``--floor``; ``--motion on`` adds the group's point's move since it was last tested;
``--robust`` tests a group of three or more on the members its point keeps. Reported per T (frames summed): ROC AUC
of right against wrong 2-view and 3-view hypotheses, one frame's score against the summed one; pair F1 of frame 0's
first packing with either score; the links' accuracy between consecutive frames; each frame's median evidence of
right and wrong hypotheses. benchmarks/README.md, "Tenth pass: several frames", has the numbers.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # run as a script: the benchmarks package beside rigsfm

import numpy as np  # noqa: E402

import rigsfm.associate.solve as solve  # noqa: E402
from benchmarks.metrics import roc_auc  # noqa: E402
from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run  # noqa: E402
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads  # noqa: E402
from rigsfm.associate.packing import _pack  # noqa: E402
from rigsfm.associate.pipeline import RunModel  # noqa: E402
from rigsfm.core.names import ImageName  # noqa: E402


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
        for name in camera_of.values():
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
    """Area under the ROC curve (``roc_auc``): the chance that a right group outscores a wrong one; NaN without both."""
    value = roc_auc(score, label)
    return float("nan") if value is None else value


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


WALK_SIGMA_M = 0.08  # per horizontal axis, a walking head's move in one frame period of 0.1 s
ACCEL_SIGMA_M = 0.03  # per horizontal axis, the change of a walking head's move from one frame to the next


def link_walk(frame_a, frame_b, gap: int, height: float, neighbours: int = 8, velocity: np.ndarray | None = None,
              margin: float = 0.0) -> np.ndarray:
    """Per detection of ``frame_a``, its nearest detection of the same view in ``frame_b`` (one to one) under the
    metric of a walk: the head stays at ``height`` and moves horizontally by ``WALK_SIGMA_M`` per axis per frame
    (``gap`` frames), carried into the image by the view's Jacobian at the detection's ray at that height (a near
    level camera sees a walk toward it hardly move the head, so the metric is long along the walk's image and short
    across it), plus both detections' noise; gated at the 99 % of two degrees of freedom. ``velocity`` (stacked
    N x 2 px a frame, NaN: unknown): where known, the head is predicted to move on at it and the metric is its
    change (``ACCEL_SIGMA_M`` per axis a frame) and the velocity's own noise. ``margin``: a link only where the
    second nearest is at least this much farther (squared, in the metric): ambiguous heads stay unlinked."""
    from scipy.spatial import cKDTree

    out = np.full(int(frame_a.offsets[-1]), -1, dtype=np.int64)
    for v, view in enumerate(frame_a.views):
        a = np.arange(frame_a.offsets[v], frame_a.offsets[v + 1])
        b = np.arange(frame_b.offsets[v], frame_b.offsets[v + 1])
        if not len(a) or not len(b):
            continue
        x = frame_a.ray_points(a, height)
        uv0, _ = view.project(x)
        eps = 0.05
        jx = (view.project(x + np.array([eps, 0.0, 0.0]))[0] - uv0) / eps
        jy = (view.project(x + np.array([0.0, eps, 0.0]))[0] - uv0) / eps
        jac = np.stack([jx, jy], axis=2)  # N x 2 (image) x 2 (floor)
        jj = np.einsum("nij,nkj->nik", jac, jac)
        noise = 2 * frame_a.options.pixel_sigma ** 2 * np.eye(2)[None]
        start = frame_a.uv[a].copy()
        cov = (WALK_SIGMA_M * gap) ** 2 * jj + noise
        if velocity is not None:
            moving = np.all(np.isfinite(velocity[a]), axis=1)
            start[moving] += velocity[a][moving] * gap
            cov[moving] = (ACCEL_SIGMA_M * gap) ** 2 * jj[moving] + noise * (1 + gap ** 2)
        inv = np.linalg.inv(cov)
        k = min(neighbours, len(b))
        _, near = cKDTree(frame_b.uv[b]).query(start, k=k)
        near = near.reshape(len(a), k)
        diff = frame_b.uv[b][near] - start[:, None]  # N x k x 2
        d2 = np.einsum("nki,nij,nkj->nk", diff, inv, diff)
        ranked = np.sort(d2, axis=1)
        best = np.argmin(d2, axis=1)
        choice = near[np.arange(len(a)), best]
        dist = d2[np.arange(len(a)), best]
        if margin > 0 and k > 1:
            dist = np.where(ranked[:, 1] >= ranked[:, 0] + margin, dist, np.inf)
        # one to one: where several detections of a chose the same b, the closest keeps it
        order = np.argsort(dist)
        taken = np.zeros(len(b), dtype=bool)
        for i in order:
            if dist[i] > 9.21 or taken[choice[i]]:
                continue
            taken[choice[i]] = True
            out[a[i]] = b[choice[i]]
    return out


def continue_groups(frame, members: np.ndarray, last_uv: np.ndarray, reach: np.ndarray, motion_px: float,
                    floor: float, previous: np.ndarray, gap: np.ndarray, previous_var: np.ndarray,
                    candidates: int = 3, motion: bool = True,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    points = np.full((g, 3), np.nan)
    variances = np.full((g, 3, 3), np.nan)
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
        repeat = len(combos)
        value, ok, where, var = frame_evidence(frame, flat, motion_px, floor,
                                               np.repeat(previous[rows], repeat, axis=0), np.repeat(gap[rows], repeat),
                                               motion, np.repeat(previous_var[rows], repeat, axis=0))
        var = var.reshape(len(rows), repeat, 3, 3)
        value, ok = value.reshape(len(rows), -1), ok.reshape(len(rows), -1)
        where = where.reshape(len(rows), repeat, 3)
        distinct = np.array([len({tuple(r) for r in t[o]}) for t, o in zip(trial, ok)])
        value = np.where(ok, value, -np.inf)
        best = np.argmax(value, axis=1)
        has = ok.any(axis=1)
        evidence[rows[has]] = value[has, best[has]] - np.log(np.maximum(distinct[has], 1))
        tested[rows[has]] = True
        chosen[rows[has]] = trial[np.flatnonzero(has), best[has]]
        points[rows[has]] = where[np.flatnonzero(has), best[has]]
        variances[rows[has]] = var[np.flatnonzero(has), best[has]]
    return evidence, tested, chosen, points, variances


ROBUST = False  # set by --robust
TRACK_MARGIN = 6.0  # track links: the second nearest at least this much farther (squared metric)
WALK_M = 0.13  # a head's farthest walk in one frame period of 0.1 s (1.3 m/s)
BOB_M = 0.03  # a walking head's height changes by about this between frames
CHANCE_M = (0.5, 0.1)  # a chance group's point jumps about this far horizontally and vertically between frames


def frame_evidence(frame, members: np.ndarray, motion_px: float, floor: float, previous: np.ndarray | None = None,
                   gap: np.ndarray | None = None, motion: bool = True, previous_cov: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per group (members in ``frame``; -1: none), the log-likelihood ratio of its residuals, one person against two
    independent walkers, and whether it had two or more members to test (else 0); with ``previous`` (the group's
    point where it was last tested, NaN: never) also of its point's move since then (a walker's step against a
    chance group's jump). Returns the evidence, tested, and the points (NaN where not tested)."""
    n = np.sum(members >= 0, axis=1)
    out = np.zeros(len(members))
    tested = n >= 2
    where = np.full((len(members), 3), np.nan)
    variance = np.full((len(members), 3, 3), np.nan)
    if not tested.any():
        return out, tested, where, variance
    m = members[tested]
    if ROBUST:
        # a group of three or more members is tested on the members its point keeps (a wrong link in one view
        # drops that member, as the frame's own verification would, instead of breaking the whole group)
        big = np.sum(m >= 0, axis=1) >= 3
        if big.any():
            kept = m.copy()
            kept[big] = frame.verify(m[big])[0]
            m = np.where(np.sum(kept >= 0, axis=1)[:, None] >= 2, kept, m)
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
    if motion and previous is not None and previous_cov is not None:
        before = previous[tested]
        steps = np.maximum(gap[tested], 1) if gap is not None else np.ones(len(m))
        move = points - before
        known = np.all(np.isfinite(move), axis=1)
        # both points' own covariances on either side (a pair's point is long along its nearly parallel rays)
        own = covariance + previous_cov[tested]
        walk = np.diag([WALK_M ** 2, WALK_M ** 2, BOB_M ** 2])
        jump = np.diag([CHANCE_M[0] ** 2, CHANCE_M[0] ** 2, CHANCE_M[1] ** 2])
        safe = np.where(known[:, None], move, 0.0)
        same_c = own + walk[None] * (steps ** 2)[:, None, None]
        chance_c = own + jump[None] * (steps ** 2)[:, None, None]
        same = -0.5 * np.einsum("ni,ni->n", safe, np.linalg.solve(same_c, safe[..., None])[..., 0]) \
            - 0.5 * np.linalg.slogdet(same_c)[1]
        chance = -0.5 * np.einsum("ni,ni->n", safe, np.linalg.solve(chance_c, safe[..., None])[..., 0]) \
            - 0.5 * np.linalg.slogdet(chance_c)[1]
        value = value + np.where(known, same - chance, 0.0)
    value = np.where((points[:, 2] >= lo) & (points[:, 2] <= hi), value, floor)
    out[tested] = np.maximum(value, floor)
    where[tested] = points
    variance[tested] = covariance
    return out, tested, where, variance


def run_seed(dataset: Path, out: Path, seed: int, frames: int, configs: list[tuple[str, bool]], motion_px: float,
             floor: float, radius_px: float, options: AssociateOptions, speed_m_s: float = 1.3,
             period_s: float = 0.1) -> dict:
    """One association of the recording, then frame 0's hypotheses followed under each (link, motion) of
    ``configs``."""
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
    prior = finals[0].options.height_prior
    head_height = prior[0] if prior is not None else float(np.mean(finals[0].options.heights))
    rows = []
    for link, motion in configs:
        f0 = finals[0]
        members, pts, cov = f0._grown[None]
        score0 = f0.score(members, pts, cov)
        ids = np.where(members >= 0, person[0][np.maximum(members, 0)], -2)
        size = np.sum(members >= 0, axis=1)
        first = np.max(np.where(members >= 0, ids, -3), axis=1)
        right = np.all((members < 0) | (ids == first[:, None]), axis=1) & (first >= 0)
        # each member's latest linked detection and its frame: a member missed in a frame is looked for again in the
        # next one from where it was last seen (the truth links frame 0 to frame k directly)
        last = members.copy()
        last_frame = np.zeros(members.shape, dtype=np.int64)
        last_uv = np.where((members >= 0)[..., None], f0.uv[np.maximum(members, 0)], np.nan)
        depth = np.stack([v.project(pts)[1] for v in f0.views], axis=1)  # G x V, the point's depth in each view
        focal = np.array([v.focal for v in f0.views])
        summed = score0.copy()
        previous, previous_frame = pts.copy(), np.zeros(len(members), dtype=np.int64)
        previous_var = cov.copy()
        tested_frames = np.zeros(len(members), dtype=np.int64)
        links: dict[tuple[int, int], np.ndarray] = {}
        link_counts = [0, 0, 0]  # right links, links, real detections

        def linked(j: int, k: int, link: str = link, links: dict[tuple[int, int], np.ndarray] = links,
                   ) -> np.ndarray:
            """Per detection of frame j, its link in frame k (-1: none), computed once."""
            if (j, k) not in links:
                if link == "truth":
                    links[(j, k)] = link_truth(finals[j], finals[k], person[j], person[k])
                elif link == "nearest":
                    links[(j, k)] = link_nearest(finals[j], finals[k], np.full(len(finals[k].views),
                                                                               radius_px * (k - j)))
                elif link == "walk":
                    links[(j, k)] = link_walk(finals[j], finals[k], k - j, head_height)
                else:
                    links[(j, k)] = link_walk(finals[j], finals[k], k - j, head_height, velocity=velocity(j),
                                              margin=TRACK_MARGIN)
            return links[(j, k)]

        def velocity(j: int, links: dict[tuple[int, int], np.ndarray] = links) -> np.ndarray | None:
            """Per detection of frame j, its move from its linked detection in frame j - 1 (px; NaN: none)."""
            step = links.get((j - 1, j))
            if step is None:
                return None
            out = np.full((int(finals[j].offsets[-1]), 2), np.nan)
            linked = np.flatnonzero(step >= 0)
            out[step[linked]] = finals[j].uv[step[linked]] - finals[j - 1].uv[linked]
            return out
        for k in range(frames):
            if k > 0 and link == "search":
                gap = k - last_frame
                reach = speed_m_s * period_s * gap * focal[None] / np.maximum(depth, 1.0) + 3 * finals[k].noise[None]
                evidence, tested, current, where, var = continue_groups(
                    finals[k], members, last_uv, reach, motion_px * k, floor, previous, k - previous_frame, previous_var,
                    motion=motion)
                found_now = current >= 0
                last_uv = np.where(found_now[..., None], finals[k].uv[np.maximum(current, 0)], last_uv)
                last_frame = np.where(found_now, k, last_frame)
                summed = summed + evidence
                tested_frames += tested
                previous = np.where(tested[:, None], where, previous)
                previous_frame = np.where(tested, k, previous_frame)
                previous_var = np.where(tested[:, None, None], var, previous_var)
            elif k > 0:
                current = np.full(members.shape, -1, dtype=np.int64)
                if link != "truth":  # how often a link between consecutive frames joins one true person's detections
                    step = linked(k - 1, k)  # every step is linked: a track's velocity comes from its last one
                    real = (person[k - 1] >= 0) & (step >= 0)
                    link_counts[0] += int(np.sum(person[k][step[real]] == person[k - 1][real]))
                    link_counts[1] += int(real.sum())
                    link_counts[2] += int(np.sum(person[k - 1] >= 0))
                for j in np.unique(last_frame[last >= 0]):
                    here = (last >= 0) & (last_frame == j)
                    current[here] = linked(int(j), k)[last[here]]
                found_now = current >= 0
                last = np.where(found_now, current, last)
                last_frame = np.where(found_now, k, last_frame)
                evidence, tested, where, var = frame_evidence(finals[k], current, motion_px * k, floor, previous,
                                                              k - previous_frame, motion, previous_var)
                summed = summed + evidence
                tested_frames += tested
                previous = np.where(tested[:, None], where, previous)
                previous_frame = np.where(tested, k, previous_frame)
                previous_var = np.where(tested[:, None, None], var, previous_var)
            medians = {}
            if k > 0:  # this frame's evidence, median over the tested right and wrong groups
                for n_views in (2, 3):
                    sel = (size == n_views) & tested & np.isfinite(score0)
                    for label, which in (("right", right), ("wrong", ~right)):
                        pick = sel & which
                        medians[f"evidence{n_views}_{label}"] = round(float(np.median(evidence[pick])), 3) \
                            if pick.any() else None
                    medians[f"tested{n_views}_wrong"] = round(float(np.mean(tested[(size == n_views) & ~right])), 3)
            row = {"seed": seed, "frames": k + 1, "link": link, "motion": motion, "single_f1_frame": round(single_f1[k], 4)}
            for n_views in (2, 3):
                sel = (size == n_views) & np.isfinite(score0)
                row[f"auc{n_views}_one"] = round(auc(score0[sel], right[sel]), 4)
                row[f"auc{n_views}_summed"] = round(auc(summed[sel], right[sel]), 4)
                row[f"right{n_views}"] = int(right[sel].sum())
                row[f"wrong{n_views}"] = int((~right[sel]).sum())
            total = int(f0.offsets[-1])
            for name, value in (("one", score0), ("summed", summed)):
                ok = value > options.min_score
                chosen = _pack(members[ok], value[ok] - options.min_score, total, options.time_limit_s)
                kept = members[ok][chosen]
                groups = [[(f0.views[v].name, int(i - f0.offsets[v])) for v, i in enumerate(m) if i >= 0] for m in kept]
                s = score_groups(groups, truths[0])
                row[f"f1_{name}"] = round(s.pair_f1, 4)
                row[f"p_{name}"] = round(s.pair_precision, 4)
                row[f"r_{name}"] = round(s.pair_recall, 4)
            row.update(medians)
            if link_counts[1]:
                row["links_right"] = round(link_counts[0] / link_counts[1], 3)
                row["linked_share"] = round(link_counts[1] / max(link_counts[2], 1), 3)
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
    parser.add_argument("--link", default="truth",
                        help="comma-separated: truth (an oracle), nearest (mutual nearest), walk (nearest under a walk's "
                        "image metric), track (walk, with each head's velocity from its last link and unambiguous links only), "
                        "search (best combination)")
    parser.add_argument("--motion-px", type=float, default=3.0,
                        help="two heads' relative motion across the epipolar line in one frame (px)")
    parser.add_argument("--radius-px", type=float, default=16.0,
                        help="nearest linking: a head's farthest move in a frame (px)")
    parser.add_argument("--period-s", type=float, default=0.1, help="the recording's frame period (s)")
    parser.add_argument("--motion", default="off", help="comma-separated: off, on (the points' move between frames)")
    parser.add_argument("--robust", action="store_true",
                        help="groups of three or more: test the members their point keeps (verify)")
    parser.add_argument("--floor", type=float, default=-8.0, help="one frame's evidence at least this")
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    options = AssociateOptions(pixel_sigma=args.pixel_sigma)
    global ROBUST
    ROBUST = args.robust
    configs = [(link, motion == "on") for link in args.link.split(",") for motion in args.motion.split(",")]
    out = [run_seed(args.dataset, args.out, s, args.frames, configs, args.motion_px, args.floor, args.radius_px,
                    options, period_s=args.period_s) for s in range(args.seeds)]
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
