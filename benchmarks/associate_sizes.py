"""A head's apparent size as evidence of its depth: the association with and without detection radii.

    python benchmarks/associate_sizes.py DATASET OUT [--seeds 2] [--noise 0.05 0.1 0.2] [--spread 0.1] [--json F]

DATASET, OUT and the detections' points as in ``benchmarks/associate.py`` (the same seed gives the same points).
Each detection also gets an apparent head radius from the truth: f R / distance from the true camera centre to the
true head centre, R the rendered head radius times a lognormal factor per person (``--spread``), times lognormal
detector noise (``--noise``); a false detection takes a random visible head's radius of its image with 20 % noise.
Per seed: the association without radii (the issue's protocol) and with them at each noise, through
``associate_frames`` (pair / person F1, head error, coverage, CPU seconds), and the ROC AUC of right against wrong
hypotheses of 2 and 3 views of the final association (right: every member one true person's), scored with and
without the size term, and the first packing's pair F1 with and without it.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # run as a script: the benchmarks package beside rigsfm

import numpy as np  # noqa: E402

from benchmarks.associate import evaluate  # noqa: E402
from benchmarks.metrics import roc_auc  # noqa: E402
from rigsfm.associate import AssociateOptions  # noqa: E402
from rigsfm.associate.evaluate import score_groups  # noqa: E402
from rigsfm.associate.frame import _Frame  # noqa: E402
from rigsfm.associate.packing import _pack  # noqa: E402


def _auc(right: np.ndarray, wrong: np.ndarray) -> float | None:
    return roc_auc(np.concatenate([right, wrong]), np.r_[np.ones(len(right), bool), np.zeros(len(wrong), bool)])


def separation(found, truth, options: AssociateOptions) -> dict:
    """AUCs and the first packing's pair F1 of the final association's hypotheses, with and without the size term."""
    views, result = found.views, found.result
    final = dataclasses.replace(options, detection_probability=result.detection_probability, occlusion=result.occlusion,
                                height_prior=result.height_prior, head_radius_m=result.head_radius_m)
    frame = _Frame(views, final, result.appearance)
    members, points, covariance, _ = frame.hypotheses()
    pid = np.concatenate([truth.person[v.name] for v in views])
    ids = np.where(members >= 0, pid[np.maximum(members, 0)], -2)
    size = np.sum(members >= 0, axis=1)
    first = np.array([row[row != -2][0] for row in ids])
    right = np.all((ids == -2) | (ids == first[:, None]), axis=1) & (first >= 0)
    plain = copy.copy(frame)
    plain.log_radius = None
    out: dict = {}
    for label, f in (("with_sizes", frame), ("without_sizes", plain)):
        if label == "with_sizes" and frame.log_radius is None:
            continue
        s = f.score(members, points, covariance)
        for k in (2, 3):
            sel = size == k
            auc = _auc(s[sel & right], s[sel & ~right])
            out[f"{label}_auc_{k}_views"] = None if auc is None else round(auc, 4)
        keep = s > final.min_score
        chosen = _pack(members[keep], s[keep] - final.min_score, int(frame.offsets[-1]), final.time_limit_s)
        groups = [[(views[v].name, int(i - frame.offsets[v])) for v, i in enumerate(m) if i >= 0]
                  for m in members[keep][chosen]]
        out[f"{label}_first_packing_pair_f1"] = round(score_groups(groups, truth).pair_f1, 4)
    out["hypotheses_2_3_views"] = [int((size == 2).sum()), int((size == 3).sum())]
    out["head_radius_m"] = result.head_radius_m
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--noise", type=float, nargs="*", default=[0.05, 0.1, 0.2])
    parser.add_argument("--no-plain", action="store_true", help="skip the association without radii")
    parser.add_argument("--spread", type=float, default=0.1)
    parser.add_argument("--pixel-sigma", type=float, default=1.5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    rows = []
    for seed in args.seeds:
        for noise in ([] if args.no_plain else [None]) + list(args.noise):
            options = AssociateOptions(pixel_sigma=args.pixel_sigma,
                                       size_noise=noise if noise is not None else 0.1,
                                       head_radius_spread=args.spread)
            ours = evaluate(args.dataset, args.out, seed, options, 1, size_noise=noise, size_spread=args.spread)
            row = {"seed": seed, "size_noise": noise, "spread": args.spread,
                   **{k: ours[k] for k in ("scores", "error_median_m", "error_p95_m", "coverage_95",
                                           "correct_persons", "cpu_seconds")},
                   **separation(ours["found"][0], ours["truth"], options)}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
