"""Is the epipolar band as wide as the truth? A Monte-Carlo over rigs.yaml's calibration error on one mapped network.

    python benchmarks/band_truth.py RESULT.json   # its summary again
    python benchmarks/band_truth.py SCENE [--draws 20] [--shape uniform|gaussian] [--inflation 3.0] [--sampled]
        [--work DIR]   # SCENE: a name of benchmarks/trust.py, prepared there (``trust.py prepare SCENE``)

The images (and so the mapping) stay as rendered; only rigs.yaml changes: each draw perturbs the exact calibration
(``rigs_exact.yaml``) as the renderer does (``uniform``: ``rigsfm.synth.cameras.perturb_rig_from``, bounded
errors) or by a Gaussian of the same sigmas (``gaussian``), writes those sigmas beside it, adjusts with the defaults and
computes every narrow pair's band. Scored per draw and pair against exact truth (400 true floor points, as
trust.py): coverage, the true distances' 95th percentile; and what the band's own model predicts for that percentile
(the median over the model's draws of a pair's p95: the number the band should be compared with when the calibration
error is one draw per pair). Pooled over draws and pairs, the coverage is the band's calibration with every error
drawn from the sigmas rigs.yaml states, which one rendered network alone cannot show. Results: WORK/band_truth/.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import zlib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from benchmarks.trust import DEFAULT_WORK, Scene, load_prepared, prepare, scenes, true_floor_points  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

logger = logging.getLogger("benchmarks.band_truth")


def variations() -> dict[str, Scene]:
    """Networks rendered unlike trust.py's (checked on, not diagnosed on): other lenses, heights, arcs, image noise,
    several frames of static rigs."""
    out = [
        Scene("v8_lens", "8-rig circle, other lenses (wide 1100 / narrow 2800 px)",
              SceneOptions(num_rigs=8, image_scale=0.5, seed=5, wide_focal=1100.0, narrow_focal=2800.0)),
        Scene("v6_high", "6 rigs on 270°, 5 m high, JPEG 85",
              SceneOptions(num_rigs=6, arc_deg=270, image_scale=0.5, seed=6, rig_height=5.0, jpeg_quality=85)),
        Scene("v3_arc", "3 rigs on 120°, exposure jitter, noise 3 grey levels",
              SceneOptions(num_rigs=3, arc_deg=120, image_scale=0.5, seed=7, exposure_jitter=0.1, noise_sigma=3.0)),
        Scene("v2_90", "2 rigs 90°", SceneOptions(num_rigs=2, arc_deg=90, image_scale=0.5, seed=8)),
        Scene("m8_3f", "8-rig circle, 3 frames of static rigs",
              SceneOptions(num_rigs=8, image_scale=0.5, seed=9, frames_per_rig=3)),
    ]
    return {s.name: s for s in out}


def all_scenes() -> dict[str, Scene]:
    return {**scenes(), **variations()}


def gaussian_rigs(exact, rng):
    """rigs.yaml whose error is a Gaussian draw of the renderer's sigmas (``calibration_error_sigmas``)."""
    import pycolmap

    from rigsfm.core.rig import RigCalibration
    from rigsfm.synth.cameras import calibration_error_sigmas

    out = []
    for rig in exact:
        sigmas = calibration_error_sigmas(rig)
        cameras = {}
        for sensor in ("wide", "narrow"):
            camera = rig.camera(sensor)
            params = np.asarray(camera.params) + rng.standard_normal(len(camera.params)) * sigmas[sensor]
            cameras[sensor] = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                                              params=params)
        w = np.radians(sigmas["rotation_deg"]) * rng.standard_normal(3)
        t = sigmas["translation_m"] * rng.standard_normal(3)
        pose = rig.narrow_from_wide
        out.append(RigCalibration(rig.name, cameras["wide"], cameras["narrow"], pycolmap.Rigid3d(
            pycolmap.Rotation3d(w) * pose.rotation, np.asarray(pose.translation) + t)))
    return out


def predicted_p95(reconstruction, covariance, bands, plane, num_samples: int = 400, seed: int = 1) -> dict:
    """Per pair: the median over the linear model's draws of the pair's 95th percentile of |d| (no pixel noise:
    the true correspondences are exact), and the model's pooled 95 % quantile."""
    from rigsfm.run.adjustment.bands import PairModel, _draw_parameters, band_points

    images = {im.name: im for im in reconstruction.images.values() if im.has_pose}
    draws = _draw_parameters(covariance, num_samples, seed)
    out = {}
    for name_i, name_j in bands:
        pixels, depths, _ = band_points(reconstruction, images[name_i], images[name_j], plane)
        model = PairModel(reconstruction, covariance, images[name_i], images[name_j], {})
        distances = np.abs(draws[:, covariance.index(model.keys)] @ model.jacobian(pixels, depths).T)
        out[(name_i, name_j)] = float(np.median(np.quantile(distances, 0.95, axis=1)))
    return out


def one_draw(prepared, exact, k: int, shape: str, inflation: float, sampled: bool, tmp: Path) -> list[dict]:
    from rigsfm.core.geometry import correspondence_check
    from rigsfm.core.rig import load_rigs
    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.adjustment.bands import narrow_pair_bands
    from rigsfm.run.adjustment.priors import calibration_priors
    from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
    from rigsfm.run.options import AdjustOptions
    from rigsfm.run.world.analysis_floor import find_floor
    from rigsfm.synth.cameras import perturb_rig_from
    from rigsfm.synth.dataset import rigs_yaml_with_sigmas

    rng = np.random.default_rng([k, 977])
    user = [perturb_rig_from(r, rng) for r in exact] if shape == "uniform" else gaussian_rigs(exact, rng)
    path = tmp / f"rigs_{k}.yaml"
    path.write_text(rigs_yaml_with_sigmas(user))
    rigs = load_rigs(path)
    priors = calibration_priors(rigs, path)
    result = adjust(prepared.mapped, rigs, prepared.inputs.scale, AdjustOptions(pixel_sigma_inflation=inflation), priors)
    plane, source = find_floor(result.reconstruction, result.scale_spec)
    unc = estimate_uncertainty(result, floor=plane, floor_source=source, sampled=sampled)
    rec, truth = result.reconstruction, prepared.truth
    linear = unc.bands if not sampled else narrow_pair_bands(rec, unc.covariance, plane=plane)
    predicted = predicted_p95(rec, unc.covariance, linear, plane)
    rows = []
    for (name_i, name_j), band in sorted(unc.bands.items()):
        prng = np.random.default_rng(zlib.crc32(f"{name_i}|{name_j}".encode()))
        d = correspondence_check(rec, truth, name_i, name_j, true_floor_points(truth, name_i, prng))
        if len(d) < 10:
            continue
        rows.append({"draw": k, "pair": [name_i, name_j], "band_px": band.band_px,
                     "linear_band_px": linear[(name_i, name_j)].band_px if (name_i, name_j) in linear else None,
                     "coverage": float(np.mean(d <= band.band_px)), "true_p95_px": float(np.quantile(d, 0.95)),
                     "predicted_p95_px": predicted.get((name_i, name_j)),
                     "predicted_below_85": band.predicted_below_85, "distances": d.tolist(),
                     "pixel_sigma": result.pixel_sigma, "held": sorted(result.held_rigs or [])})
    return rows


def summarise(rows: list[dict]) -> dict:
    bands = np.array([r["band_px"] for r in rows])
    p95 = np.array([r["true_p95_px"] for r in rows])
    pooled = np.concatenate([np.asarray(r["distances"]) <= r["band_px"] for r in rows])
    coverage = np.array([r["coverage"] for r in rows])
    predicted = np.array([r["predicted_p95_px"] or np.nan for r in rows])
    shrink = 1.15 * np.median(p95) / np.median(bands)  # the band scaled to the 1.15x the true p95
    shrunk = np.concatenate([np.asarray(r["distances"]) <= shrink * r["band_px"] for r in rows])
    per_draw = [np.mean(np.concatenate([np.asarray(r["distances"]) <= r["band_px"] for r in rows if r["draw"] == k]))
                for k in sorted({r["draw"] for r in rows})]
    return {"pairs": len(rows), "draws": len({r["draw"] for r in rows}), "pooled_coverage": float(pooled.mean()),
            "band_median_px": float(np.median(bands)), "true_p95_median_px": float(np.median(p95)),
            "band_over_true_p95": float(np.median(bands) / np.median(p95)),
            "median_of_ratio": float(np.median(bands / p95)),
            "model_band_over_predicted_p95": float(np.nanmedian(bands / predicted)),
            "observed_below_85": float(np.mean(coverage < 0.85)),
            "predicted_below_85": float(np.mean([r["predicted_below_85"] for r in rows])),
            "pooled_coverage_at_1.15x": float(shrunk.mean()),
            "draws_covering_99.8": float(np.mean(np.array(per_draw) >= 0.998)),
            "per_draw_coverage_range": [float(np.min(per_draw)), float(np.max(per_draw))]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--shape", choices=("uniform", "gaussian"), default="uniform")
    parser.add_argument("--inflation", type=float, default=3.0)
    parser.add_argument("--sampled", action="store_true", help="the sampled band (default: as the run decides)")
    parser.add_argument("--linear", action="store_true", help="the linear band whatever the network's size")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK)
    parser.add_argument("--tag", default="")
    parser.add_argument("--independent-views", action="store_true",
                        help="count a static rig's repeated views as independent (the covariance before "
                             "rigsfm.run.adjustment.repeated)")
    args = parser.parse_args()
    if args.independent_views:
        import rigsfm.run.adjustment.covariance as covariance

        covariance.repeated_view_correlation = lambda *a, **k: {}
        args.tag += "_independent"
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logger.setLevel(logging.INFO)
    from rigsfm.core.rig import load_rigs

    if args.scene.endswith(".json"):  # a saved result: its summary again
        print(json.dumps(summarise(json.loads(Path(args.scene).read_text())["rows"]), indent=1))
        return
    scene = all_scenes()[args.scene]
    prepare(scene, args.work)
    prepared = load_prepared(scene, args.work)
    exact = load_rigs(args.work / "scenes" / scene.name / "scene" / "rigs_exact.yaml")
    out = args.work / "band_truth"
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "tmp"
    tmp.mkdir(exist_ok=True)
    sampled = True if args.sampled else (False if args.linear else None)
    rows = []
    for k in range(args.first, args.first + args.draws):
        t = time.perf_counter()
        new = one_draw(prepared, exact, k, args.shape, args.inflation, sampled, tmp)
        rows += new
        logger.info("draw %d: %d pairs, %.0f s, running %s", k, len(new), time.perf_counter() - t,
                    {a: round(b, 3) for a, b in summarise(rows).items() if not isinstance(b, list)})
    tag = f"{scene.name}_{args.shape}_i{args.inflation:g}{'_sampled' if args.sampled else ''}{'_linear' if args.linear else ''}{args.tag}"
    (out / f"{tag}.json").write_text(json.dumps({"summary": summarise(rows), "rows": rows}))
    print(tag, json.dumps(summarise(rows), indent=1))


if __name__ == "__main__":
    main()
