"""The association with each view's detection probability from the crowd's occlusion (measured, not landed).

    python benchmarks/associate_visibility.py DATASET OUT [--seeds 2] [--first-seed 0] [--pixel-sigma 1.5]

The score's detection probability is one number for every view (the crowd's, rigsfm.associate.rates). Here, once the
crowd's rates are estimated (after the self-calibration), each view's probability of detecting a point X becomes
``q exp(-a I_v(X))``: ``I_v`` the expected heads-and-shoulders (per unit density) the ray from camera v to X passes
under, inside the crowd's footprint (a disc round the persons' median, out to their 99th percentile radius), a
person's top standing above the ray's height with the probability the crowd's height prior gives; ``q`` and ``a`` the
maximum-likelihood fit of the confident persons' detected / not detected views. A member then scores ``log p_v(X)``
and a view seeing X without a member ``log(1 - p_v(X))``, in place of the constant ``log p_d`` and ``log(1 - p_d)``;
the frame is associated once more with it. Frame 0, detections as benchmarks/associate.py makes them. The library is
patched in this process only (``_crowd_rates`` and ``_Frame.score``); benchmarks/README.md, *Twenty-first pass*.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.stats import norm

import rigsfm.associate.solve as solve_module
from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads
from rigsfm.associate.frame import _Frame

STEPS = np.arange(0.3, 16.0, 0.1)  # metres back from X towards the camera, along the floor
ORIGINAL_SCORE, ORIGINAL_RATES = _Frame.score, solve_module._crowd_rates
MODEL: dict = {}


def occluders(centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per row, the expected persons (per unit density x width, m) standing above the ray from ``centres`` to
    ``points`` inside the footprint."""
    out = np.empty(len(points))
    mean, sigma = MODEL["heights"]
    for a in range(0, len(points), 4000):
        c, x = centres[a:a + 4000], points[a:a + 4000]
        back = c[:, :2] - x[:, :2]
        length = np.maximum(np.linalg.norm(back, axis=1), 1e-6)
        slope = (c[:, 2] - x[:, 2]) / length
        at = x[:, None, :2] + STEPS[None, :, None] * (back / length[:, None])[:, None, :]
        inside = (np.linalg.norm(at - MODEL["centre"], axis=2) < MODEL["radius"]) & (STEPS[None] < length[:, None] - 0.5)
        ray = x[:, 2:3] + STEPS[None] * slope[:, None]
        # a person's head top ~0.1 m above its point, its shoulders ~0.15 m below: the ray passes through either
        above = norm.sf(ray - 0.05, loc=mean, scale=sigma)
        out[a:a + 4000] = 0.1 * np.sum(inside * above, axis=1)
    return out


def _fit(frame: _Frame, members: np.ndarray, points: np.ndarray, scores: np.ndarray, heights: tuple) -> None:
    """The footprint from the persons, q and a from the confident ones' detected and missed views."""
    MODEL.clear()
    MODEL["heights"] = heights
    # the footprint from every person (the confident ones alone stand nearer the centre: 7.7 m on crowd8, less F1)
    MODEL["centre"] = np.median(points[:, :2], axis=0)
    MODEL["radius"] = float(np.percentile(np.linalg.norm(points[:, :2] - MODEL["centre"], axis=1), 99))
    size = np.sum(members >= 0, axis=1)
    confident = (size >= 3) & (scores > 0)
    x = points[confident]
    depth, detected = [], []
    for v, view in enumerate(frame.views):
        uv, z = view.project(x)
        seen = view.inside(uv, z) | (members[confident, v] >= 0)
        depth.append(occluders(np.repeat(frame.centres[v][None], int(seen.sum()), axis=0), x[seen]))
        detected.append(members[confident, v][seen] >= 0)
    d, hit = np.concatenate(depth), np.concatenate(detected)
    best = None
    for q in np.linspace(0.5, 0.99, 50):
        for a in np.linspace(0.0, 4.0, 81):
            p = q * np.exp(-a * d)
            ll = float(np.sum(np.where(hit, np.log(np.maximum(p, 1e-9)), np.log(np.maximum(1 - p, 1e-9)))))
            if best is None or ll > best[0]:
                best = (ll, q, a)
    assert best is not None
    MODEL["q"], MODEL["a"] = float(best[1]), float(best[2])
    MODEL["person_views"] = len(d)


def patched_rates(state: tuple, options: AssociateOptions, given: AssociateOptions) -> AssociateOptions:
    estimated = ORIGINAL_RATES(state, options, given)
    frame, members, points, _, scores, _ = state
    if estimated.height_prior is not None and len(points):
        _fit(frame, members, points, scores, estimated.height_prior)
        # associated again under the new probabilities, whether or not the rates changed
        estimated = dataclasses.replace(estimated, time_limit_s=estimated.time_limit_s * (1 + 1e-12))
    return estimated


def patched_score(self, members, points, covariance, misses=True, floor=None):
    if not MODEL:
        return ORIGINAL_SCORE(self, members, points, covariance, misses=misses, floor=floor)
    p_d = self.options.detection_probability
    present = members >= 0
    k = present.sum(axis=1)
    total = ORIGINAL_SCORE(self, members, points, covariance, misses=False) - k * math.log(p_d)
    bound = total + k * math.log(MODEL["q"])  # every p_v(X) <= q, every miss costs
    rows = np.flatnonzero(bound > floor) if floor is not None else np.arange(len(total))
    for v, view in enumerate(self.views):
        uv, z = view.project(points[rows])
        at = rows[view.inside(uv, z) | present[rows, v]]
        if not len(at):
            continue
        p = MODEL["q"] * np.exp(-MODEL["a"] * occluders(np.repeat(self.centres[v][None], len(at), axis=0),
                                                          points[at]))
        member = present[at, v]
        total[at[member]] += np.log(np.maximum(p[member], 1e-6))
        if misses:
            total[at[~member]] += np.log(np.maximum(1 - p[~member], 1e-6))
    if floor is not None:
        keep = np.zeros(len(total), dtype=bool)
        keep[rows] = True
        total[~keep | (total <= floor)] = -np.inf
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--first-seed", type=int, default=0, help="the detections' seeds from this one on")
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    args = parser.parse_args(argv)
    model = load_run(args.out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(args.dataset, "frame0000").items() if n in sizes}
    solve_module._crowd_rates = patched_rates  # type: ignore[assignment]
    _Frame.score = patched_score  # type: ignore[method-assign]
    try:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            MODEL.clear()
            truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed)
            found = associate_frames(model, from_arrays(truth.points), AssociateOptions(pixel_sigma=args.pixel_sigma))[0]
            groups = [[(found.views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in found.result.members]
            s = score_groups(groups, truth)
            print(json.dumps({"seed": seed, "pair_f1": round(s.pair_f1, 4), "pair_precision": round(s.pair_precision, 4),
                              "pair_recall": round(s.pair_recall, 4), "person_f1": round(s.person_f1, 4),
                              "cpu_seconds": round(found.cpu_seconds, 1),
                              "model": {k: (np.round(v, 3).tolist() if isinstance(v, np.ndarray) else v)
                                        for k, v in MODEL.items()}}), flush=True)
    finally:
        solve_module._crowd_rates, _Frame.score = ORIGINAL_RATES, ORIGINAL_SCORE  # type: ignore[assignment,method-assign]
    return 0


if __name__ == "__main__":
    sys.exit(main())
