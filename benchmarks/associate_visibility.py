"""The association with and without each view's detection probability from the crowd's occlusion.

    python benchmarks/associate_visibility.py DATASET OUT [--seeds 2] [--first-seed 0] [--pixel-sigma 1.5]

The score's detection probability of a point X in view v is ``q exp(-a I_v(X))`` (``AssociateOptions.visibility``,
the default; rigsfm.associate.rates.Occlusion: ``I_v`` the persons per unit density whose heads or shoulders stand
above the ray from camera v to X inside the crowd's footprint, ``q`` and ``a`` fitted on the confident persons with the
crowd's rates), against one probability for every view (``visibility=False``). Frame 0, detections as
benchmarks/associate.py makes them; per seed both associations' pair and person F1, CPU seconds and the fitted model.
benchmarks/README.md, *Twenty-first pass* (the measurement as a patch) and *Twenty-second pass* (in the library).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads


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
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed)
        for visibility in (False, True):
            options = AssociateOptions(pixel_sigma=args.pixel_sigma, visibility=visibility)
            found = associate_frames(model, from_arrays(truth.points), options)[0]
            groups = [[(found.views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in found.result.members]
            s = score_groups(groups, truth)
            occlusion = found.result.occlusion
            print(json.dumps({"seed": seed, "visibility": visibility, "pair_f1": round(s.pair_f1, 4),
                              "pair_precision": round(s.pair_precision, 4), "pair_recall": round(s.pair_recall, 4),
                              "person_f1": round(s.person_f1, 4), "cpu_seconds": round(found.cpu_seconds, 1),
                              "occlusion": dataclasses.asdict(occlusion) if occlusion is not None else None}),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
