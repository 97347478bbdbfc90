# ruff: noqa: E701, E702
"""The floor's reported sigma against the render's truth (benchmarks/README.md, 2026-11-28): gauge-free floor normal
(per camera, and the cameras' rotation-only mean) and camera heights, z-scores against summary.json's floor sigmas.

    PYTHONPATH=. python benchmarks/floor_sigma_measure.py [--table] RUN_ROOT...   (RUN_ROOT holding scene/ and run/)

``--table``: one markdown row per run (the sparse floors' table: where the floor's points came from, its sigmas and
their basis, the normal's error and z, the narrow heights within 1.96 of their reported sigma) instead of the JSON.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.synth.truth import _posed


def rot_mean(Rs):
    M = sum(Rs); U, _, Vt = np.linalg.svd(M); R = U @ Vt
    if np.linalg.det(R) < 0: U[:, -1] *= -1; R = U @ Vt
    return R

def measure(root):
    root = Path(root)
    est = pycolmap.Reconstruction(str(root / "run/sparse")); gt = pycolmap.Reconstruction(str(root / "scene/ground_truth"))
    s = json.load(open(root / "run/summary.json")); f = s["world"]["floor"]
    ns, hs = f["normal_sigma_deg"], f["camera_height_sigma"]
    z = np.array([0, 0, 1.0]); out = {"run": root.name, "normal_sigma_deg": ns, "height_sigma_mm": 1000 * hs,
                                      "floor_points": f["points_by_source"], "markers_mm": [1000 * m for m in f.get("marker_residuals", [])],
                                      "matched": f["matching"]["ran"], "sigma_basis": f.get("sigma_basis"),
                                      "num_groups": f.get("num_groups"), "effective_groups": f.get("effective_groups"),
                                      "grouped_normal_sigma_deg": f.get("grouped_normal_sigma_deg"),
                                      "pose_normal_sigma_deg": f.get("pose_normal_sigma_deg"),
                                      "scatter_normal_sigma_deg": f.get("scatter_normal_sigma_deg")}
    for sensor in ("wide", "narrow", "all"):
        if sensor == "all":
            e = {**_posed(est, "wide"), **_posed(est, "narrow")}; g = {**_posed(gt, "wide"), **_posed(gt, "narrow")}
        else:
            e, g = _posed(est, sensor), _posed(gt, sensor)
        names = sorted(set(e) & set(g))
        Re = {n: e[n].cam_from_world().rotation.matrix() for n in names}
        Rg = {n: g[n].cam_from_world().rotation.matrix() for n in names}
        # per camera: the floor normal in the camera's own frame, estimated vs true
        per = [np.degrees(np.arccos(np.clip((Re[n] @ z) @ (Rg[n] @ z), -1, 1))) for n in names]
        # rotation-only alignment (no centres, no scale): est_world_from_true_world = mean of Re^T Rg
        A = rot_mean([Re[n].T @ Rg[n] for n in names])
        tilt = np.degrees(np.arccos(np.clip((A @ z) @ z, -1, 1)))
        u = A @ z
        # residual camera rotation scatter about that alignment (tilt component only, per camera)
        out[sensor] = {"n": len(names), "normal_err_per_camera_deg": {"median": float(np.median(per)), "max": float(np.max(per))},
                       "normal_err_aligned_deg": float(tilt), "z_normal": float(tilt / ns)}
        if sensor == "narrow" or sensor == "wide":
            he = np.array([e[n].projection_center()[2] for n in names]); hg = np.array([g[n].projection_center()[2] for n in names])
            d = 1000 * (he - hg)
            if sensor == "narrow":
                unc = s["uncertainty"]["narrow"]
                zc = []
                for n in names:
                    C = np.array(unc[n]["centre_covariance_mm2"]); R = Re[n]
                    zc.append(np.sqrt((R.T @ C @ R)[2, 2]))
                zc = np.array(zc); comb = np.sqrt(zc**2 + (1000 * hs)**2)
                out[sensor]["centre_vertical_sigma_mm"] = {"min": float(zc.min()), "max": float(zc.max())}
                out[sensor]["z_height_combined_max"] = float(np.max(np.abs(d) / comb))
                out[sensor]["frac_within_95_combined"] = float(np.mean(np.abs(d) <= 1.96 * comb))
                if "narrow_camera_heights" in f:  # the run's own per-camera height sigma (floor's part + own centre's)
                    reported = np.array([1000 * f["narrow_camera_heights"][n]["sigma_m"] for n in names])
                    out[sensor]["z_height_reported_max"] = float(np.max(np.abs(d) / reported))
                    out[sensor]["frac_within_95_reported"] = float(np.mean(np.abs(d) <= 1.96 * reported))
                    # the floor's part and the camera's own in quadrature alone (before the poses' height: pose_sigma_m)
                    entries = [f["narrow_camera_heights"][n] for n in names]
                    parts = np.array([1000 * np.hypot(e["floor_sigma_m"], e["own_sigma_m"]) for e in entries])
                    out[sensor]["z_height_floor_own_max"] = float(np.max(np.abs(d) / parts))
                    out[sensor]["frac_within_95_floor_own"] = float(np.mean(np.abs(d) <= 1.96 * parts))
            out[sensor].update({"height_err_mm": {"min": float(d.min()), "median": float(np.median(d)), "max": float(d.max()),
                                "max_abs": float(np.abs(d).max())}, "z_height_max": float(np.abs(d).max() / (1000 * hs)),
                                "frac_within_95": float(np.mean(np.abs(d) <= 1.96 * 1000 * hs))})
            # decompose: scale (ratio of centre distances) and tilt (plane fit of the height errors over the arena)
            if sensor == "wide":
                Ce = np.array([e[n].projection_center() for n in names]); Cg = np.array([g[n].projection_center() for n in names])
                i, j = np.triu_indices(len(names), 1)
                de = np.linalg.norm(Ce[i] - Ce[j], axis=1); dg = np.linalg.norm(Cg[i] - Cg[j], axis=1)
                sc = float(np.median(de / dg) - 1)
                X = np.c_[np.ones(len(names)), Cg[:, 0], Cg[:, 1]]
                coef, *_ = np.linalg.lstsq(X, d / 1000, rcond=None)
                res = d / 1000 - X @ coef
                out["scale_err_percent"] = 100 * sc
                Xe = np.c_[np.ones(len(names)), Ce[:, 0], Ce[:, 1]]
                ce, *_ = np.linalg.lstsq(Xe, d / 1000, rcond=None)
                out["height_gradient_est_xy_deg"] = [float(np.degrees(ce[1])), float(np.degrees(ce[2]))]
                out["minus_true_up_xy_from_rotations_deg"] = [float(-np.degrees(u[0])), float(-np.degrees(u[1]))]
                T = pycolmap.estimate_sim3d(Ce, Cg)
                out["sim3_centre_residual_mm"] = [float(1000 * np.linalg.norm(T * c - cg)) for c, cg in zip(Ce, Cg)]
                out["sim3_tilt_deg"] = float(np.degrees(np.arccos(np.clip((T.rotation.matrix().T @ z) @ z, -1, 1))))
                out["height_err_from_scale_mm"] = float(1000 * sc * np.median(hg))
                out["height_plane_fit"] = {"offset_mm": 1000 * coef[0], "slope_deg": float(np.degrees(np.hypot(coef[1], coef[2]))),
                                           "residual_rms_mm": float(1000 * np.sqrt(np.mean(res**2)))}
    return out

def table_row(r):
    """The sparse floors' table (benchmarks/README.md, 2026-11-28): run, floor points (sparse / matched / markers),
    pairs (effective), the normal's error, the pairs' and the poses' sigmas and the reported one (z), the narrow
    heights' errors, within 1.96 of sqrt(floor's part^2 + own^2) and of the reported ``sigma_m`` (max z)."""
    p, n = r["floor_points"], r["narrow"]
    z = lambda s: f"{s:.4f} ({r['all']['normal_err_aligned_deg'] / s:.2f})" if s else "-"  # noqa: E731
    return (f"| {r['run']} | {p['sparse']} / {p['matched']} / {p['markers']} | {r['num_groups']} "
            f"({r['effective_groups']:.1f}) | {r['all']['normal_err_aligned_deg']:.4f} | "
            f"{z(r['grouped_normal_sigma_deg'])} | {z(r['pose_normal_sigma_deg'])} | {z(r['normal_sigma_deg'])} | "
            f"{n['height_err_mm']['min']:+.0f} .. {n['height_err_mm']['max']:+.0f} | "
            f"{round(n.get('frac_within_95_floor_own', float('nan')) * n['n'])}/{n['n']} "
            f"({n.get('z_height_floor_own_max', float('nan')):.2f}) | "
            f"{round(n.get('frac_within_95_reported', float('nan')) * n['n'])}/{n['n']} "
            f"({n.get('z_height_reported_max', float('nan')):.2f}) |")


if __name__ == "__main__":
    table = "--table" in sys.argv[1:]
    rows = [measure(r) for r in sys.argv[1:] if r != "--table"]
    print("\n".join(map(table_row, rows)) if table else json.dumps(rows, indent=1))
