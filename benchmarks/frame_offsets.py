"""Frame-offset estimation (rigsfm.run.checks.sync) on rendered recordings with known per-rig offsets.

    python benchmarks/frame_offsets.py WORK     # JSON lines: true and estimated offsets, per-pair scores

Five rigs round a floor whose fine texture moves rigidly 25 cm along x and y per frame (a flat walking crowd,
tests/test_sync.py), narrow images rendered exactly, rig r's frame k at time k + offset; bands 1 px.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import cv2
import numpy as np
import pycolmap
from synthetic_world import ring
from test_floor_matching import render
from test_self_check import fine_texture
from test_sync import STEP_TEXELS, recording

from rigsfm.core.names import name_of
from rigsfm.run.checks.sync import estimate_frame_offsets
from rigsfm.run.deliver import narrow_poses
from rigsfm.run.options import WorldOptions
from rigsfm.run.world.frame import place_in_world

base = ring(seed=42, num_rigs=5, model_from_truth=pycolmap.Rigid3d(), narrow_model="PINHOLE").reconstruction
place_in_world(base, None, None, ["rig01"], WorldOptions())
texture = fine_texture(seed=3)
cases = [{}, {"rig03": 1}, {"rig02": 2}, {"rig01": -1}, {"rig02": 1, "rig04": -1}, {"rig05": 0.5}, {"rig04": -2}]
for frames in (3, 4):
    rec = recording(base, frames)
    poses = narrow_poses(rec, metric=True, world={"frame": "floor"})
    for p in poses["pairs"]:
        p["epipolar_band_95_px"] = 1.0
    for n, offsets in enumerate(cases):
        if frames == 4 and n not in (0, 6):
            continue
        root = Path(sys.argv[1]) / f"f{frames}c{n}"
        for image in rec.images.values():
            parsed = name_of(image)
            if not parsed.is_narrow:
                continue
            t = int(parsed.frame[5:9]) + offsets.get(parsed.rig, 0)
            s = int(round(STEP_TEXELS * t))
            path = root / image.name
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), render(image, np.roll(texture, (s, s), axis=(0, 1))))
        e = estimate_frame_offsets(rec, root, poses)
        print(json.dumps({"frames": frames, "true": offsets, "estimated": e.offsets, "named": e.unsynchronised,
                          "clear": e.clear, "seconds": round(e.seconds, 1),
                          "pairs": [(p.a, p.b, [(s.d, s.matches, s.consistent and round(s.consistent, 2)) for s in p.scores]) for p in e.pairs]}), flush=True)
