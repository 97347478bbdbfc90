"""Cross-validation over tracks as the hold-or-refine decision, measured against today's default and
``--fixed-calibration``.

    python benchmarks/calibration_cv.py [--bench WORK] [--networks NAME ...] [--hor HOR_WORK] [--hor-scenes NAME ...]
        [--folds 5] --out FILE

The same scenes as ``benchmarks/influence_rule.py`` (read only). Per scene: today's default adjustment (``adjust``,
the influential-track rule in) and its decisions, the rigs it held ``H``; the model it last refined every rig of (the
mapping model less the tracks the rule removed). Where ``H`` is not every rig, K-fold cross-validation over that
model's tracks (``point3D_id`` permuted with a fixed seed, K folds): per fold, the model less the fold's tracks
adjusted twice at today's pixel noise, once with the rigs ``H`` held (today's choice) and once with every rig held
(the calibration at rigs.yaml's values, in the same adjustment); each held-out track is triangulated again with each
fold's cameras and poses (DLT in the undistorted rays, then Gauss-Newton on the pixel residuals) and its reprojection
errors taken. The prediction error of each choice: the sum over held-out observations of the squared error clipped
at ``max_reprojection_error_px`` (a wrong click counts as one outlier under both), and of the robust loss (Cauchy at
``loss_scale_px``). The CV decision: hold every rig where the held calibration predicts the held-out tracks better
(no threshold: two predictions compared), else today's. Scores against the exact truth as ``influence_rule.py``; on
the ``hold_or_refine`` scenes also with the narrow intrinsics and E^sl of both results set to rigs_exact.yaml's
(``*_exact_narrow``: the wide poses' share of the narrow error).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

import rigsfm.run.adjustment.adjust as adjust_module  # noqa: E402
from benchmarks.hold_or_refine import cached_mapping_models, epipolar_p95  # noqa: E402
from benchmarks.networks import default_mapping_models  # noqa: E402
from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.core.names import name_of  # noqa: E402
from rigsfm.core.rig import load_rigs  # noqa: E402
from rigsfm.run.adjustment.model import frames_without_points  # noqa: E402
from rigsfm.run.options import AdjustOptions, Calibration  # noqa: E402
from rigsfm.synth.truth import compare_to_ground_truth  # noqa: E402

logger = logging.getLogger("benchmarks.calibration_cv")


def retriangulated_errors(rec: pycolmap.Reconstruction, tracks: list[list[tuple[int, np.ndarray]]],
                          iterations: int = 8) -> np.ndarray:
    """Per observation of ``tracks`` (lists of (image_id, xy)), its reprojection error (px) after triangulating the
    track with ``rec``'s cameras and poses; inf where an image is not registered or a point lands behind a camera."""
    images = {i: im for i, im in rec.images.items() if im.has_pose}
    obs_track, obs_image, obs_xy = [], [], []
    for t, track in enumerate(tracks):
        for image_id, xy in track:
            obs_track.append(t)
            obs_image.append(image_id)
            obs_xy.append(xy)
    obs_track_a, obs_image_a, obs_xy_a = np.array(obs_track), np.array(obs_image), np.array(obs_xy, dtype=float)
    valid = np.array([i in images for i in obs_image_a])
    poses = {i: images[i].cam_from_world().matrix() for i in images}
    # undistorted normalised rays, for the DLT
    rays = np.zeros((len(obs_xy_a), 2))
    for image_id in np.unique(obs_image_a[valid]):
        on = obs_image_a == image_id
        rays[on] = rec.cameras[images[image_id].camera_id].cam_from_img(obs_xy_a[on])
    points = np.full((len(tracks), 3), np.nan)
    for t in range(len(tracks)):
        on = np.flatnonzero((obs_track_a == t) & valid)
        if len(on) < 2:
            continue
        rows = []
        for o in on:
            p = poses[obs_image_a[o]]
            rows.append(rays[o, 0] * p[2] - p[0])
            rows.append(rays[o, 1] * p[2] - p[1])
        _, _, vt = np.linalg.svd(np.array(rows))
        if abs(vt[-1, 3]) > 1e-12:
            points[t] = vt[-1, :3] / vt[-1, 3]

    def project(xyz: np.ndarray) -> np.ndarray:
        out = np.full((len(obs_xy_a), 2), np.nan)
        for image_id in np.unique(obs_image_a[valid]):
            on = obs_image_a == image_id
            p = poses[image_id]
            cam = xyz[obs_track_a[on]] @ p[:, :3].T + p[:, 3]
            front = cam[:, 2] > 1e-9
            projected = np.full((len(cam), 2), np.nan)
            if front.any():
                projected[front] = rec.cameras[images[image_id].camera_id].img_from_cam(cam[front])
            out[on] = projected
        return out - obs_xy_a

    # Gauss-Newton per point (numeric Jacobian, all points at once)
    for _ in range(iterations):
        residual = project(points)
        jac = np.zeros((len(obs_xy_a), 2, 3))
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = 1e-6 * (1.0 + np.nanmax(np.abs(points))) if np.isfinite(points).any() else 1e-6
            jac[:, :, axis] = (project(points + step) - residual) / step[axis]
        ok = np.isfinite(residual).all(axis=1) & np.isfinite(jac).all(axis=(1, 2)) & valid
        jtj = np.zeros((len(tracks), 3, 3))
        jtr = np.zeros((len(tracks), 3))
        np.add.at(jtj, obs_track_a[ok], np.einsum("oia,oib->oab", jac[ok], jac[ok]))
        np.add.at(jtr, obs_track_a[ok], np.einsum("oia,oi->oa", jac[ok], residual[ok]))
        solvable = np.linalg.det(jtj) > 1e-18
        delta = np.zeros_like(points)
        delta[solvable] = np.linalg.solve(jtj[solvable] + 1e-9 * np.eye(3), -jtr[solvable][..., None])[..., 0]
        points = points + np.nan_to_num(delta)
    residual = project(points)
    errors = np.linalg.norm(residual, axis=1)
    errors[~valid | ~np.isfinite(errors)] = np.inf
    return errors


def cross_validate(base: pycolmap.Reconstruction, inputs, options: AdjustOptions, held: frozenset[str],
                   pixel_sigma: float, folds: int) -> dict:
    """Prediction errors of the held-out tracks: today's choice (``held``) and every rig held."""
    all_rigs = frozenset(r.name for r in inputs.rigs)
    point_ids = np.array(sorted(base.points3D))
    rng = np.random.default_rng(0)
    fold_of = dict(zip(point_ids.tolist(), rng.permutation(len(point_ids)) % folds))
    sums = {"today": {"clipped": 0.0, "cauchy": 0.0, "n": 0}, "held": {"clipped": 0.0, "cauchy": 0.0, "n": 0}}
    clip2 = options.max_reprojection_error_px ** 2
    per_fold = []
    for k in range(folds):
        out = [pid for pid in point_ids.tolist() if fold_of[pid] == k]
        train = pycolmap.Reconstruction(base)
        for pid in out:
            train.delete_point3D(pid)
        if frames_without_points(train):
            logger.warning("fold %d: a frame loses every point; skipped", k)
            continue
        tracks = [[(el.image_id, np.asarray(base.images[el.image_id].points2D[el.point2D_idx].xy))
                   for el in base.points3D[pid].track.elements] for pid in out]
        fold_row = {}
        for label, rigs_held in (("today", held), ("held", all_rigs)):
            result = adjust_module._refine(train, inputs.rigs, inputs.scale, options, inputs.priors, rigs_held,
                                           held_noise=pixel_sigma)
            errors = retriangulated_errors(result.reconstruction, tracks)
            e2 = np.minimum(errors ** 2, clip2)
            cauchy = np.log1p(np.minimum(errors ** 2, 1e12) / options.loss_scale_px ** 2)
            sums[label]["clipped"] += float(e2.sum())
            sums[label]["cauchy"] += float(cauchy.sum())
            sums[label]["n"] += int(len(errors))
            fold_row[label] = float(e2.sum())
        per_fold.append(fold_row)
    return {"today": sums["today"], "held": sums["held"], "per_fold": per_fold}


def with_exact_narrow(rec: pycolmap.Reconstruction, exact) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with every narrow camera's intrinsics and E^sl at ``exact``'s (rigs_exact.yaml): what is left
    of its narrow error is its wide poses' (and scale's)."""
    rec = pycolmap.Reconstruction(rec)
    by_name = {r.name: r for r in exact}
    for image in rec.images.values():
        name = name_of(image)
        if name.is_narrow:
            camera = rec.cameras[image.camera_id]
            camera.params = by_name[name.rig].camera(name.sensor).params
            rec.rig(rec.frame(image.frame_id).rig_id).set_sensor_from_rig(camera.sensor_id,
                                                                           by_name[name.rig].narrow_from_wide)
    return rec


def scores(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    rotation = compare_to_ground_truth(rec, truth, "narrow")["relative_rotation_deg"]
    return {"rotation_max_deg": rotation["max"], "epipolar_p95_px": epipolar_p95(rec, truth)}


def measure(name: str, mapped, truth, inputs, folds: int, exact=None) -> dict:
    calls: list = []
    original = adjust_module._refine

    def recording(model, rigs, scale_spec, options, priors, held, *args, **kwargs):
        if not held:
            calls.append(model)
        return original(model, rigs, scale_spec, options, priors, held, *args, **kwargs)

    adjust_module._refine = recording
    try:
        t = time.perf_counter()
        today = adjust_module.adjust(pycolmap.Reconstruction(mapped), inputs.rigs, inputs.scale, AdjustOptions(),
                                     inputs.priors)
        seconds_today = time.perf_counter() - t
    finally:
        adjust_module._refine = original
    fixed = adjust_module.adjust(pycolmap.Reconstruction(mapped), inputs.rigs, inputs.scale,
                                 AdjustOptions(calibration=Calibration.FIXED), inputs.priors)
    held = frozenset(d.rig for d in today.decisions if d.held)
    row: dict = {"network": name, "tracks": mapped.num_points3D(), "rigs": len(today.decisions),
                 "held_today": len(held), "calibration_today": str(today.calibration),
                 "today": scores(today.reconstruction, truth), "fixed": scores(fixed.reconstruction, truth),
                 "seconds_today": seconds_today}
    if exact is not None:
        row["today_exact_narrow"] = scores(with_exact_narrow(today.reconstruction, exact), truth)
        row["fixed_exact_narrow"] = scores(with_exact_narrow(fixed.reconstruction, exact), truth)
    if len(held) == len(today.decisions) or today.pixel_sigma is None or not calls:
        row["cv"] = None
        row["decision"] = "held (today)"
        return row
    t = time.perf_counter()
    cv = cross_validate(calls[-1], inputs, AdjustOptions(), held, today.pixel_sigma, folds)
    row["cv"] = cv
    row["cv_seconds"] = time.perf_counter() - t
    row["decision"] = "hold" if cv["held"]["clipped"] < cv["today"]["clipped"] else "today"
    row["decision_cauchy"] = "hold" if cv["held"]["cauchy"] < cv["today"]["cauchy"] else "today"
    logger.info("%s: %s", name, {k: v for k, v in row.items() if k != "cv"} | {
        "cv": {k: cv[k] for k in ("today", "held")}})
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", type=Path, default=None)
    parser.add_argument("--networks", nargs="*", default=None)
    parser.add_argument("--hor", type=Path, default=None)
    parser.add_argument("--hor-scenes", nargs="*", default=None)
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(name)s %(levelname)s %(message)s")
    logger.setLevel(logging.INFO)
    rows = json.loads(args.out.read_text())["rows"] if args.out.exists() else []
    done = {r["network"] for r in rows}
    if args.hor is not None:
        for label, scene, dataset, inputs, mapped in cached_mapping_models(args.hor, args.hor_scenes, done):
            t = time.perf_counter()
            exact = load_rigs(scene / "scene" / "rigs_exact.yaml")
            rows.append(measure(label, mapped, dataset.load_ground_truth(), inputs, args.folds, exact))
            print(f"{label}: {time.perf_counter() - t:.0f} s {rows[-1]['decision']}", flush=True)
            write_json_atomic(args.out, {"rows": rows}, overwrite=True)
    if args.bench is not None:
        names = args.networks or sorted(p.name for p in args.bench.iterdir())
        for name, inputs, truth, mapped in default_mapping_models(args.bench, names, done):
            t = time.perf_counter()
            rows.append(measure(name, mapped, truth, inputs, args.folds))
            print(f"{name}: {time.perf_counter() - t:.0f} s {rows[-1]['decision']}", flush=True)
            write_json_atomic(args.out, {"rows": rows}, overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
