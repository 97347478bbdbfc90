"""Poses of the fixed-calibration stage on ``tests/synthetic_db.perturbed_model`` (three cases), for
tests/test_trust.py::test_fixed_calibration_reproduces_the_poses_before_priors.

fixed_calibration_golden.json was made with rigsfm as it was before the calibration priors (commit 6297bc6):

    git archive 6297bc6 rigsfm | tar -x -C BASE
    PYTHONPATH=BASE:tests python tests/data/fixed_calibration_golden.py OUT   # -> OUT/golden.json

(with a second argument it runs today's adjust with ``--fixed-calibration``; both agree bit for bit).
"""
import json
import sys
from pathlib import Path

import numpy as np
from synthetic_db import make_network, perturbed_model

from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.inputs.scale_file import CameraDistance, ScaleSpec

root = Path(sys.argv[1])
root.mkdir(parents=True, exist_ok=True)
kw = {}
if len(sys.argv) > 2:
    from rigsfm.run.options import AdjustOptions, Calibration
    kw = {"options": AdjustOptions(calibration=Calibration.FIXED)}
out = {}
for case in ("measurements", "none", "narrow_baselines"):
    (root / case).mkdir(exist_ok=True)
    net = make_network(root / case, num_rigs=4, seed=21, narrow_observations=case == "narrow_baselines")
    mapped = perturbed_model(net.ground_truth, 21, narrow_observations=case == "narrow_baselines",
                             scale=1.0 if case == "narrow_baselines" else 0.37)
    a, b = "rig01/wide/frame0000.png", "rig03/wide/frame0000.png"
    gt = net.ground_truth
    m = float(np.linalg.norm(gt.find_image_with_name(a).projection_center() - gt.find_image_with_name(b).projection_center()))
    spec = ScaleSpec(root / "scale.yaml", (CameraDistance(a, b, m),), ()) if case == "measurements" else None
    r = adjust(mapped, net.rigs, spec, **kw)
    out[case] = {"scale_source": str(r.scale_source), "scale_relative_sigma": r.scale_relative_sigma,
                 "cam_from_world": {im.name: np.asarray(im.cam_from_world().matrix()).tolist()
                                    for im in sorted(r.reconstruction.images.values(), key=lambda im: im.name)}}
json.dump(out, open(root / "golden.json", "w"), indent=1)
