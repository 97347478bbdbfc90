"""Why the refined calibration moves further than its posterior allows (``CALIBRATION CONTRADICTED`` false alarms):
the hold-or-refine test's chi-square on a network's first refined pass, against the exact truth, and a Monte-Carlo
of the same network with exact keypoints.

    python benchmarks/change_spread.py WORK/NETWORK [--classes] [--draws N] [--correlation R] [--inflation X]
        [--out FILE]

``WORK/NETWORK`` is a folder of ``benchmarks/networks.py`` (``scene/`` rendered, ``default/mapping`` the default
run's mapping model, read only). Each row is the first refined pass of that mapping model (``adjust._refine``, every
rig refined, no track removed), its covariance and :func:`hold_or_refine`: the network's chi-square with the test's
null as delivered (``prior - posterior``) and as it was before ``JointCovariance.change_excess`` ("posterior only"),
the pixel noise, and the refined calibration's error against rigs_exact.yaml whitened by the posterior.

- ``--classes``: the truth's classes of tracks (``crowd_band.classify``: static, person, contour, inconsistent); the
  pass again with only the static tracks, and with the tracks whose largest truth residual exceeds 1 px removed, the
  noise held at the every-track pass's; the static tracks' truth residuals (px per coordinate).
- ``--draws N``: N Monte-Carlo draws on the same network: every track's point triangulated with the true cameras,
  its keypoints replaced by their exact projections plus Gaussian noise of the every-track pass's estimated sigma
  (the share ``--correlation`` of the variance shared by a camera's repeated views of one point, as a static
  rig's frames share a keypoint's error), and rigs.yaml drawn afresh from a Gaussian of its own sigmas about the
  exact calibration; the pass and its test on each. Were the test's null right, the chi-square over its dof
  averages 1 (the 95 % test fails on 5 % of draws). ``--inflation``: ``AdjustOptions.pixel_sigma_inflation``;
  ``--oracle-noise``: the adjustment and the covariance weigh by the draws' own sigma, not by its estimate.

Results and what they say: benchmarks/README.md, "Why the refined calibration moves further than its posterior".
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
from scipy.stats import chi2 as chi2_distribution  # noqa: E402

from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.run.adjustment import adjust as adjust_module  # noqa: E402
from rigsfm.run.adjustment.covariance import joint_covariance  # noqa: E402
from rigsfm.run.adjustment.decisions import HOLD_QUANTILE, hold_or_refine  # noqa: E402
from rigsfm.run.options import AdjustOptions  # noqa: E402
from rigsfm.run.pipeline import load_inputs  # noqa: E402

logger = logging.getLogger("benchmarks.change_spread")


def first_pass(mapped, rigs, inputs, options, held_noise=None, exact=None) -> dict:
    """The first refined pass of ``mapped`` at ``rigs`` (every rig refined), its test with and without the
    estimator's excess spread, and (``exact`` given) the refined calibration's error against it."""
    start = time.perf_counter()
    result = adjust_module._refine(mapped, rigs, inputs.scale, options, inputs.priors, frozenset(),
                                   held_noise=held_noise)
    cov = joint_covariance(result)
    result.rigs = tuple(rigs)
    new = hold_or_refine(result, cov)
    old = hold_or_refine(result, replace(cov, change_excess=None))
    row = {"pixel_sigma": result.pixel_sigma, "points": result.reconstruction.num_points3D(),
           "seconds": time.perf_counter() - start}
    for label, decisions in (("delivered", new), ("posterior_only", old)):
        tested = [d for d in decisions if d.network_dof]
        if tested:
            d = tested[0]
            row[label] = {"chi2": d.network_chi2, "dof": d.network_dof,
                          "limit": float(chi2_distribution.ppf(HOLD_QUANTILE, d.network_dof)),
                          "per_rig": {x.rig: [x.chi2, x.dof] for x in decisions}}
    if exact is not None:
        from benchmarks.crowd_band import calibration_errors

        row["error_vs_truth"] = calibration_errors(result, cov, exact)
    logger.info("pass: sigma %.3f px, chi2 %s / %s (posterior only %s / %s), %.0f s", result.pixel_sigma,
                row.get("delivered", {}).get("chi2"), row.get("delivered", {}).get("dof"),
                row.get("posterior_only", {}).get("chi2"), row.get("posterior_only", {}).get("dof"), row["seconds"])
    return row


def true_points(mapped: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict[int, np.ndarray]:
    """Per 3D point of ``mapped``: its track triangulated with the true cameras (linear, then Gauss-Newton)."""
    views = {}
    for image_id, image in mapped.images.items():
        true_image = truth.find_image_with_name(image.name)
        if true_image is not None:
            views[image_id] = (truth.cameras[true_image.camera_id], true_image.cam_from_world())
    out = {}
    for pid, point in mapped.points3D.items():
        obs = [(views[e.image_id], np.asarray(mapped.image(e.image_id).points2D[e.point2D_idx].xy))
               for e in point.track.elements if e.image_id in views]
        if len(obs) < 2:
            continue
        rows = []
        for (camera, pose), xy in obs:
            ray = np.asarray(camera.cam_ray_from_img(xy), dtype=float)
            m = pose.matrix()
            rows.append(ray[0] * m[2] - ray[2] * m[0])
            rows.append(ray[1] * m[2] - ray[2] * m[1])
        _, _, vt = np.linalg.svd(np.array(rows))
        x = vt[-1][:3] / vt[-1][3]
        for _ in range(5):
            jac, res = [], []
            for (camera, pose), xy in obs:
                proj = camera.img_from_cam(pose * x)
                if proj is None:
                    break
                res.append(np.asarray(proj) - xy)
                jac.append(np.column_stack([(np.asarray(camera.img_from_cam(pose * (x + h))) - proj) / 1e-6
                                            for h in np.eye(3) * 1e-6]))
            else:
                step = np.linalg.lstsq(np.vstack(jac), -np.concatenate(res), rcond=None)[0]
                x = x + step
                continue
            break
        out[pid] = x
    return out


def exact_keypoints(mapped, truth, points, sigma, correlation, rng) -> pycolmap.Reconstruction:
    """``mapped`` with every kept track's keypoints at their exact projections plus Gaussian noise ``sigma`` per
    coordinate, the share ``correlation`` of its variance common to one camera's views of the point; tracks without
    a true point deleted."""
    rec = pycolmap.Reconstruction(mapped)
    for pid in list(rec.points3D):
        if pid not in points:
            rec.delete_point3D(pid)
            continue
        shared: dict[int, np.ndarray] = {}
        projections = []
        for e in rec.points3D[pid].track.elements:
            image = rec.image(e.image_id)
            true_image = truth.find_image_with_name(image.name)
            camera = truth.cameras[true_image.camera_id]
            projections.append((image, e.point2D_idx, camera.img_from_cam(true_image.cam_from_world() * points[pid])))
        if any(proj is None for _, _, proj in projections):
            rec.delete_point3D(pid)
            continue
        for image, idx, proj in projections:
            common = shared.setdefault(image.camera_id, rng.normal(0.0, sigma * np.sqrt(correlation), 2))
            image.points2D[idx].xy = np.asarray(proj) + common + rng.normal(0.0, sigma * np.sqrt(1 - correlation), 2)
    return rec


def gaussian_rigs(exact, priors, rng, narrow_from_wide: bool = True):
    """rigs.yaml drawn from a Gaussian of its sigmas about the exact calibration (E^sl: rotation vector and
    translation from its 6x6 covariance; ``narrow_from_wide`` False: the intrinsics alone, E^sl exact)."""
    out = []
    for rig in exact:
        cameras = {}
        for sensor in ("wide", "narrow"):
            given, sigmas = rig.camera(sensor), priors[rig.name].sensor(sensor)
            cameras[sensor] = pycolmap.Camera(model=given.model_name, width=given.width, height=given.height,
                                              params=np.asarray(given.params)
                                              + sigmas * rng.standard_normal(len(sigmas)))
        if not narrow_from_wide:
            out.append(replace(rig, wide=cameras["wide"], narrow=cameras["narrow"]))
            continue
        draw = rng.multivariate_normal(np.zeros(6), priors[rig.name].narrow_from_wide)
        given = rig.narrow_from_wide
        turn = pycolmap.Rotation3d(pycolmap.Rigid3d(pycolmap.Rotation3d(draw[:3]), np.zeros(3)).rotation.matrix()
                                   @ given.rotation.matrix())
        out.append(replace(rig, wide=cameras["wide"], narrow=cameras["narrow"],
                           narrow_from_wide=pycolmap.Rigid3d(turn, np.asarray(given.translation) + draw[3:])))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("network", type=Path)
    parser.add_argument("--classes", action="store_true")
    parser.add_argument("--draws", type=int, default=0)
    parser.add_argument("--correlation", type=float, default=0.0)
    parser.add_argument("--inflation", type=float, default=None)
    parser.add_argument("--sigma", type=float, default=None, help="--draws: the keypoints' noise (px per coordinate)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--oracle-noise", action="store_true",
                        help="--draws: the adjustment and the covariance use the draws' own sigma, not the residuals'")
    parser.add_argument("--skip-real", action="store_true")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    for noisy in ("rigsfm", "pycolmap"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    scene = args.network / "scene"
    inputs = load_inputs(scene / "images", scene / "rigs.yaml", scene / "scale.yaml")
    exact = load_inputs(scene / "images", scene / "rigs_exact.yaml", scene / "scale.yaml")
    truth = pycolmap.Reconstruction(str(scene / "ground_truth"))
    mapped = pycolmap.Reconstruction(str(args.network / "default" / "mapping"))
    options = AdjustOptions()
    if args.inflation is not None:
        options = replace(options, pixel_sigma_inflation=args.inflation)
    out: dict = {"network": args.network.name, "inflation": options.pixel_sigma_inflation}
    if not args.skip_real:
        out["every_track"] = first_pass(mapped, inputs.rigs, inputs, options, exact=exact)
    if args.classes:
        from benchmarks.crowd_band import classify, scene_options

        classes = classify(mapped, truth, scene_options(scene))
        counts: dict[str, int] = {}
        for c in classes.values():
            counts[c["class"]] = counts.get(c["class"], 0) + 1
        static = [r for c in classes.values() if c["class"] == "static" for r in c["residuals"]]
        out["classes"] = counts
        out["static_truth_residual_px"] = {"median": float(np.median(static)),
                                           "rms_per_coordinate": float(np.sqrt(np.mean(np.square(static)) / 2))}
        noise = out["every_track"]["pixel_sigma"]  # the estimated noise (the weighting noise over the inflation)
        for label, drop in (("static_only", lambda c: c["class"] != "static"),
                            ("truth_residual_le_1px", lambda c: not c["residuals"] or max(c["residuals"]) > 1.0)):
            rec = pycolmap.Reconstruction(mapped)
            removed = 0
            for pid, c in classes.items():
                if drop(c):
                    rec.delete_point3D(pid)
                    removed += 1
            out[label] = {"removed": removed, **first_pass(rec, inputs.rigs, inputs, options, held_noise=noise,
                                                            exact=exact)}
    if args.draws:
        rng = np.random.default_rng(args.seed)
        points = true_points(mapped, truth)
        sigma = args.sigma or (out["every_track"]["pixel_sigma"]
                               if "every_track" in out else 0.15)
        if args.oracle_noise:  # the noise model the draws follow, not its estimate from the residuals
            import rigsfm.run.adjustment.repeated as repeated_module

            adjust_module.estimate_pixel_sigma = repeated_module.estimate_pixel_sigma = lambda *_a, **_k: sigma
        draws = []
        for k in range(args.draws):
            rec = exact_keypoints(mapped, truth, points, sigma, args.correlation, rng)
            rigs = gaussian_rigs(exact.rigs, inputs.priors, rng)
            draws.append(first_pass(rec, rigs, inputs, options, exact=exact))
            summary = {}
            for label in ("delivered", "posterior_only"):
                ratios = [d[label]["chi2"] / d[label]["dof"] for d in draws if label in d]
                fails = [d[label]["chi2"] > d[label]["limit"] for d in draws if label in d]
                summary[label] = {"chi2_over_dof_mean": float(np.mean(ratios)), "fails_95": int(np.sum(fails)),
                                  "draws": len(ratios)}
            truth_ratio = [d["error_vs_truth"]["chi2_over_dof"] for d in draws]
            summary["posterior_error_chi2_over_dof_mean"] = float(np.mean(truth_ratio))
            out["monte_carlo"] = {"sigma": sigma, "correlation": args.correlation, "tracks": len(points),
                                  "oracle_noise": args.oracle_noise,
                                  "summary": summary, "draws": draws}
            logger.info("draw %d: %s", k, json.dumps(summary))
    path = args.out or args.network / "change_spread.json"
    write_json_atomic(path, out, overwrite=True)
    print(json.dumps({k: v for k, v in out.items() if k != "monte_carlo"}, indent=1, default=str)[:6000])
    if "monte_carlo" in out:
        print(json.dumps(out["monte_carlo"]["summary"], indent=1))


if __name__ == "__main__":
    main()
