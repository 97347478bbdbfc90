# ruff: noqa: E702
"""(benchmarks/README.md, 2026-11-28; PYTHONPATH=. python benchmarks/floor_sigma_cause.py RUN_ROOT) Which error tilts the floor relative to the cameras: the recorded floor matches re-triangulated with
(poses, intrinsics) from (run, truth) in each combination; every point is carried into the truth's frame through
camera i's own pose (no world alignment), a plane fitted to the points of the run's floor inliers."""
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

import rigsfm.run.world.floor_matching as fm

root = Path(sys.argv[1])
est = pycolmap.Reconstruction(str(root / "run/sparse")); gt = pycolmap.Reconstruction(str(root / "scene/ground_truth"))
matches = fm.match_floor_points(est, root / "scene/images", np.array([0, 0, 1.0]), 0.0)
rec, start = [], 0
for m in matches.matches:  # the kept matches' pixels, pair after pair, in the points' order
    rec.append((m.image_i, m.image_j, m.xy_i, m.xy_j, matches.points[start:start + len(m.xy_i)]))
    start += len(m.xy_i)
f = json.load(open(root / "run/summary.json"))["world"]["floor"]

def hybrid(poses, intr):
    r = pycolmap.Reconstruction(poses)
    other = {im.name: im for im in intr.images.values()}
    for im in r.images.values():
        r.cameras[im.camera_id].params = other[im.name].camera.params
    return {im.name: im for im in r.images.values()}
E = {im.name: im for im in est.images.values()}; G = {im.name: im for im in gt.images.values()}
variants = {"run poses + run intrinsics": hybrid(est, est), "run poses + true intrinsics": hybrid(est, gt),
            "true poses + run intrinsics": hybrid(gt, est), "true poses + true intrinsics": hybrid(gt, gt)}
kept = np.vstack([r[4] for r in rec]); print("z of matched points (m) pct 10,50,90:", np.percentile(kept[:, 2], [10, 50, 90]).round(4), "t", f["threshold"]); inl = np.abs(kept[:, 2] - np.median(kept[:, 2])) < f["threshold"]
lab = np.concatenate([np.full(len(r[4]), k, dtype=int) for k, r in enumerate(rec)])
print("points", len(kept), "inliers (|z|<t of the run's floor)", int(inl.sum()), "from", len(np.unique(lab[inl])), "pairs; largest 3 hold",
      int(np.sort(np.bincount(lab[inl]))[-3:].sum()))
good = {}
for name, ims in reversed(list(variants.items())):
    pts = []
    for (a, b, xa, xb, _) in rec:
        P = fm.triangulate_pairs(ims[a], ims[b], xa, xb) if len(xa) else np.zeros((0, 3))
        # into the truth's frame through camera a's pose of this variant -> truth pose of camera a
        Ta = ims[a].cam_from_world(); Ga = G[a].cam_from_world()
        pts.append(np.array([Ga.inverse() * (Ta * p) for p in P]).reshape(-1, 3))
    P = np.vstack(pts)[inl]
    if not good:  # true poses + true intrinsics first: keep the matches that are truly on the floor (|z| < 2 cm)
        good["ok"] = np.isfinite(P).all(axis=1) & (np.abs(np.nan_to_num(P[:, 2], nan=1.0)) < 0.02)
        print("truly on the floor (|z| < 2 cm with the true poses):", int(good["ok"].sum()), "of", len(P))
    ok = good["ok"] & np.isfinite(P).all(axis=1); P = P[ok]
    X = np.c_[np.ones(len(P)), P[:, 0], P[:, 1]]; c, *_ = np.linalg.lstsq(X, P[:, 2], rcond=None)
    res = P[:, 2] - X @ c
    per = [float(np.median(P[lab[inl][ok] == k, 2])) for k in np.unique(lab[inl])]
    print(f"{name:32s} tilt {np.degrees(np.hypot(c[1], c[2])):.4f} deg, offset {1000*c[0]:+.1f} mm, scatter {1000*np.sqrt(np.mean(res**2)):.1f} mm,"
          f" per-pair median height (mm) {np.round(1000*np.array(per),1).tolist()}")
K = kept[inl][good["ok"]]
X = np.c_[np.ones(len(K)), K[:, 0], K[:, 1]]; c, *_ = np.linalg.lstsq(X, K[:, 2], rcond=None)
print(f"the same floor points in the delivered model (final poses) against the delivered floor z=0: plane offset {1000*c[0]:+.1f} mm, tilt {np.degrees(np.hypot(c[1], c[2])):.4f} deg")
