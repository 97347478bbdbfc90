"""Frame-offset estimation (rigsfm.run.checks.sync, .subframe) on rendered recordings with known per-rig offsets.

    python benchmarks/frame_offsets.py WORK     # JSON lines: true and estimated offsets, per-pair scores

Five rigs round a floor whose fine texture moves rigidly 25 cm along x and y per frame (a flat walking crowd,
tests/test_sync.py), narrow images rendered exactly, rig r's frame k at time k + offset (any real offset: the
texture moves continuously, tests/test_sync.render_at); bands 1 px. Per rig: the integer estimate, the whole
estimate (integer + fraction) with its standard error, and its error against the truth.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import cv2
import pycolmap
from synthetic_world import ring
from test_self_check import fine_texture
from test_sync import recording, render_at

from rigsfm.core.names import name_of
from rigsfm.run.checks.sync import estimate_frame_offsets
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import WorldOptions
from rigsfm.run.world.frame import place_in_world

base = ring(seed=42, num_rigs=5, model_from_truth=pycolmap.Rigid3d(), narrow_model="PINHOLE").reconstruction
place_in_world(base, None, None, ["rig01"], WorldOptions())
texture = fine_texture(seed=3)
cases = {3: [{}, {"rig03": 1}, {"rig02": 2}, {"rig01": -1}, {"rig02": 1, "rig04": -1}, {"rig05": 0.5}, {"rig04": -2},
             {"rig02": 0.5, "rig03": -0.3, "rig04": 1.25}, {"rig01": 0.5}, {"rig03": 0.1}, {"rig05": -0.75}],
         4: [{}, {"rig04": -2}, {"rig02": 0.5, "rig03": -0.3, "rig04": 1.25}]}
for frames, offsets_list in cases.items():
    rec = recording(base, frames)
    poses = narrow_poses(rec, metric=True, world={"frame": "floor"})
    for p in poses["pairs"]:
        p["epipolar_band_95_px"] = 1.0
    for n, offsets in enumerate(offsets_list):
        root = Path(sys.argv[1]) / f"f{frames}c{n}"
        for image in rec.images.values():
            parsed = name_of(image)
            if not parsed.is_narrow:
                continue
            path = root / image.name
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), render_at(image, texture, int(parsed.frame[5:9]) + offsets.get(parsed.rig, 0)))
        e = estimate_frame_offsets(rec, root, poses)
        sub = e.subframe
        whole = {r: None if o is None else round(o, 3) for r, o in sub.offsets.items()} if sub else {}
        errors = {r: None if o is None else round(o - offsets.get(r, 0), 3) for r, o in whole.items()}
        print(json.dumps({"frames": frames, "true": offsets, "estimated": e.offsets, "unsynchronised": e.unsynchronised,
                          "whole": whole, "sigma": sub and {r: s and round(s, 3) for r, s in sub.sigmas.items()},
                          "error": errors, "named": {r: round(o, 2) for r, o in e.named.items()},
                          "seconds": round(e.seconds, 1),
                          "subframe_seconds": sub and round(sub.seconds, 1), "warning": e.warning,
                          "fractions": sub and [(p.a, p.b, p.d, p.tau and round(p.tau, 3), p.inliers, p.reason)
                                                for p in sub.pairs],
                          "pairs": [(p.a, p.b, [(s.d, s.matches, s.consistent and round(s.consistent, 2))
                                                for s in p.scores]) for p in e.pairs]}), flush=True)
