"""The second adjustment's band on crowds of 3D persons (narrow observations from heads) against the truth.

    python benchmarks/head_band.py SCENE [--rerun] [--out results.json]

``SCENE``: a rendered crowd (``benchmarks/narrow_observations.py``'s ``persons8c``: ground_truth/, persons/heads.csv,
rigs.yaml). The first call runs ``rigsfm run`` (defaults, ``--narrow auto``) into ``SCENE_auto`` and keeps the second
adjustment (its AdjustResult and the bands' analysis floor) in ``SCENE_auto/second.pkl``; later calls reuse it
(``--rerun``: run again). Then, against the exact truth (400 true floor correspondences per pair,
``benchmarks.trust.score_bands``): the delivered band (summary.json) and the second adjustment's band, the latter
without and with a shared error of the heads per view (``--shared-sigma OFFSET[,TILT] ...``;
``rigsfm.run.adjustment.heads_error``), with the model's own probability of a pooled coverage at most the one
observed (its draws); and per narrow view its head observations' mean error against the true head centres
(persons/heads.csv, the nearest within 8 px), the offset the model is of.
"""

from __future__ import annotations

import argparse
import json
import logging
import pickle
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
import yaml  # noqa: E402

from benchmarks.head_candidates import true_heads  # noqa: E402

logger = logging.getLogger("head_band")


def run_and_keep(scene: Path, out: Path) -> None:
    """``rigsfm run`` (defaults) on ``scene``, keeping the second adjustment in ``out / second.pkl``."""
    import rigsfm.run.pipeline as pipeline
    from benchmarks.narrow_observations import dataset, floor_scale
    from rigsfm.run.options import RunOptions

    original = pipeline.second_pass

    def keeping(result, world, *args, **kwargs):
        second, record = original(result, world, *args, **kwargs)
        if second is not result:
            floor, source = world.analysis_floor(second.reconstruction, second.scale_spec)
            (out / "second.pkl").write_bytes(pickle.dumps({"result": second, "floor": floor, "source": source}))
        return second, record

    # a rendered scene, reused with its own seed and scale (floor_scale writes that seed's bar and rangefinder)
    options = yaml.safe_load((scene / "scene.yaml").read_text(encoding="utf-8"))["options"]
    data = dataset(scene.parent, scene.name, float(options["image_scale"]), int(options["seed"]))
    pipeline.second_pass = keeping  # type: ignore[assignment]
    try:
        import shutil

        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        pipeline.run(data.images, data.rigs, out, floor_scale(data), RunOptions())
    finally:
        pipeline.second_pass = original  # type: ignore[assignment]


def band_rows(rec, truth, bands) -> dict:
    from benchmarks.trust import score_bands

    rows = score_bands(rec, truth, bands)
    rows = [r for r in rows if r["pair"][0].split("/")[0] != r["pair"][1].split("/")[0]]
    n = sum(r["num_true_points"] for r in rows)
    return {"pairs": len(rows), "coverage": sum(r["coverage"] * r["num_true_points"] for r in rows) / n,
            "band_median_px": float(np.median([r["band_px"] for r in rows])),
            "true_p95_median_px": float(np.median([r["true_p95_px"] for r in rows])),
            "below_85": sum(r["coverage"] < 0.85 for r in rows), "rows": rows,
            "model_p_at_or_below": _model_p(bands, rows, n)}


def _model_p(bands, rows, n) -> float | None:
    """The model's own probability (its draws, shared by the pairs) that the pooled coverage is at most the one
    observed: one network is one draw of its errors."""
    draws = [np.asarray(bands[tuple(r["pair"])].predicted_coverage) for r in rows]
    if not draws or any(d.size < 2 for d in draws):
        return None
    per_draw = sum(d * r["num_true_points"] for d, r in zip(draws, rows)) / n
    return float(np.mean(per_draw <= sum(r["coverage"] * r["num_true_points"] for r in rows) / n))


def _head_keypoints(rec: pycolmap.Reconstruction, point_ids, truth: dict[str, np.ndarray]):
    """Per head observation: (image, point2D index, keypoint, nearest true head centre or None beyond 8 px)."""
    for point_id in point_ids:
        if not rec.exists_point3D(point_id):
            continue
        for element in rec.points3D[point_id].track.elements:
            image = rec.image(element.image_id)
            xy = np.asarray(image.points2D[element.point2D_idx].xy)  # both COLMAP pixels
            d = truth.get(image.name, np.full((1, 2), np.inf)) - xy
            k = int(np.argmin(np.hypot(d[:, 0], d[:, 1])))
            yield image, element.point2D_idx, xy, (xy + d[k] if np.hypot(*d[k]) < 8.0 else None)


def replaced(result, scene: Path, how: str, noise_px: float, seed: int):
    """The second adjustment done again from its own model with its heads' keypoints replaced (a diagnostic:
    which part of the heads' error the band misses): ``true`` = the true centres plus independent normal noise of
    ``noise_px``; ``no-offset`` = the real keypoints less their view's mean error; ``no-tilt`` = less their view's
    affine fit of it (offset and tilt)."""
    from rigsfm.run.adjustment.adjust import adjust

    rec = pycolmap.Reconstruction(result.reconstruction)
    truth = true_heads(scene, 0.0)
    rng = np.random.default_rng(seed)
    found = [(image.name, index, xy, true) for image, index, xy, true in _head_keypoints(rec, result.point_sigmas,
                                                                                           truth) if true is not None]
    fits = {}
    for name in {f[0] for f in found}:
        rows = np.array([[*f[2], *(f[2] - f[3])] for f in found if f[0] == name])
        basis = np.c_[np.ones(len(rows)), rows[:, :2]] if how == "no-tilt" else np.ones((len(rows), 1))
        fits[name] = np.linalg.lstsq(basis, rows[:, 2:], rcond=None)[0]
    for name, index, xy, true in found:
        if how == "true":
            new = true + rng.normal(0.0, noise_px, 2)
        else:
            basis = np.r_[1.0, xy] if how == "no-tilt" else np.ones(1)
            new = xy - basis @ fits[name]
        rec.find_image_with_name(name).points2D[index].xy = new
    return adjust(rec, result.rigs, result.scale_spec, result.options, result.priors,
                  point_sigmas=result.point_sigmas)


def head_errors(rec: pycolmap.Reconstruction, point_ids, scene: Path) -> dict:
    """Per narrow image: its head observations' keypoints against the nearest true head centre (heads.csv, COLMAP
    pixels; within 8 px), mean and spread (px)."""
    errors: dict[str, list] = {}
    for image, _, xy, true in _head_keypoints(rec, point_ids, true_heads(scene, 0.0)):
        if true is not None:
            errors.setdefault(image.name, []).append(xy - true)
    out = {}
    for name, e in sorted(errors.items()):
        e = np.array(e)
        out[name] = {"n": len(e), "mean": e.mean(0).round(3).tolist(), "sd": e.std(0, ddof=1).round(3).tolist()
                     if len(e) > 1 else None}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--rerun", action="store_true")
    parser.add_argument("--replace", default=None, metavar="true|no-offset|no-tilt",
                        help="score the second adjustment done again with its heads' keypoints replaced (replaced())")
    parser.add_argument("--noise", type=float, default=None, help="--replace true: px (default: the heads' sigma)")
    parser.add_argument("--seed", type=int, default=0, help="--replace true: the noise's draw")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--shared-sigma", nargs="*", default=[], metavar="OFFSET[,TILT]",
                        help="the heads' shared error per view (px: its offset, and its tilt at the edge of the view's "
                             "heads; AdjustResult.point_shared_sigma) to score the second band at, beside none")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
    from rigsfm.synth.truth import compare_to_ground_truth

    out = args.scene.parent / f"{args.scene.name}_auto"
    if args.rerun or not (out / "second.pkl").exists():
        run_and_keep(args.scene, out)
    kept = pickle.loads((out / "second.pkl").read_bytes())
    result = kept["result"]
    truth = pycolmap.Reconstruction(str(args.scene / "ground_truth"))
    summary = json.loads((out / "summary.json").read_text())
    delivered = {(p["i"], p["j"]): type("Band", (), {"band_px": p["band_px"], "points": p["points"],
                                                     "predicted_below_85": p["predicted_below_85"],
                                                     "predicted_coverage": np.zeros(1)})
                 for p in summary["uncertainty"]["pairs"] if p.get("band_px") is not None}
    if args.replace:
        sigma = args.noise or summary["narrow_observations"]["head_sigma_px"]
        result = replaced(result, args.scene, args.replace, sigma, args.seed)
    rec = result.reconstruction
    narrow = compare_to_ground_truth(rec, truth, "narrow")["relative_rotation_deg"]
    report: dict = {"scene": str(args.scene), "rotation_deg": [narrow["median"], narrow["max"]],
                    "delivered": band_rows(pycolmap.Reconstruction(str(out / "sparse")), truth, delivered)}
    errors = head_errors(rec, result.point_sigmas, args.scene)
    report["head_errors"] = errors
    means = np.array([e["mean"] for e in errors.values() if e["n"] >= 5])
    report["head_bias_rms_px"] = float(np.sqrt(np.mean(means**2))) if len(means) else None
    keys = ["delivered"]
    for given in ["0", *args.shared_sigma]:
        offset, tilt = (float(v) for v in f"{given},0".split(",")[:2])
        result.covariance, result.point_shared_sigma, result.point_shared_slope_sigma = None, offset, tilt
        second = estimate_uncertainty(result, floor=kept["floor"], floor_source=kept["source"])
        keys.append(f"second, shared offset {offset:.3g} px, tilt {tilt:.3g} px")
        report[keys[-1]] = band_rows(rec, truth, second.bands)
    for key in keys:
        r = report[key]
        print(f"{key}: coverage {100 * r['coverage']:.1f} % over {r['pairs']} pairs ({r['below_85']} below 85 %), "
              f"band median {r['band_median_px']:.2f} px, true p95 median {r['true_p95_median_px']:.2f} px, "
              f"model's P(<= observed) {r['model_p_at_or_below']}")
    print("rotation median / max", report["rotation_deg"], "head sigma", summary["narrow_observations"].get(
        "head_sigma_px"), "head bias rms (per view, per coordinate)", report["head_bias_rms_px"])
    for name, e in errors.items():
        print(f"  {name}: {e}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
