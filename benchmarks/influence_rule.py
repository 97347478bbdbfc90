"""The default adjustment with and without the influential-track rule, against ``--fixed-calibration``.

    python benchmarks/influence_rule.py --bench WORK [--networks NAME ...] [--hor HOR_WORK] [--hor-scenes NAME ...]
        [--both] --out FILE

``WORK/<network>`` are ``benchmarks/networks.py``'s folders (``scene/`` rendered, ``default/mapping`` the default
run's mapping model, ``WORK/results/<network>.json`` the runs' scores); ``HOR_WORK/<scene>`` are
``benchmarks/hold_or_refine.py``'s cached scenes (read only: a scene not mapped there is skipped). Per network, from
the same mapping model: the default adjustment (``adjust.adjust``, this checkout: the rule in, ``after``) and, when it
removed tracks (or with ``--both``), the same with the rule off (``MAX_TRACK_INFLUENCE`` infinite: main's adjustment,
``before``); and ``--fixed-calibration``'s adjustment of the same model (``fixed_same_mapping``). Scores against the
exact truth: narrow relative-rotation error median / max (deg), the worst narrow pair's true epipolar p95 (px,
``hold_or_refine.epipolar_p95``), the bands' pooled coverage at every depth (``crowd_band.band_experiment``'s
"depths": the adjustment's own covariance, cross-rig pairs), and the fixed run's rotation max and p95 from
``WORK/results`` (``fixed_run``, the reference issue 34 names: its own pipeline run).
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

import pycolmap  # noqa: E402

import rigsfm.run.adjustment.adjust as adjust_module  # noqa: E402
from benchmarks.hold_or_refine import cached_mapping_models, epipolar_p95  # noqa: E402
from benchmarks.networks import default_mapping_models  # noqa: E402
from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.run.adjustment.covariance import joint_covariance  # noqa: E402
from rigsfm.run.options import AdjustOptions, Calibration  # noqa: E402
from rigsfm.synth.truth import compare_to_ground_truth  # noqa: E402

logger = logging.getLogger("benchmarks.influence_rule")
FIRST = ["persons4_90_s0", "persons8_360_s0", "persons8_360_s1", "plain8_360_s0", "flat8_360_s0", "shift5_80_s2"]


def coverage(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, cov) -> float | None:
    from benchmarks.trust import score_bands
    from rigsfm.run.adjustment.bands import narrow_pair_bands

    if cov is None:
        return None
    rows = [r for r in score_bands(rec, truth, narrow_pair_bands(rec, cov))
            if r["pair"][0].split("/")[0] != r["pair"][1].split("/")[0]]
    n = sum(r["num_true_points"] for r in rows)
    return sum(r["coverage"] * r["num_true_points"] for r in rows) / n if n else None


def score(mapped, truth, inputs, options: AdjustOptions, rule: bool, with_coverage: bool) -> dict:
    adjust_module.MAX_TRACK_INFLUENCE = RULE if rule else float("inf")
    t = time.perf_counter()
    result = adjust_module.adjust(pycolmap.Reconstruction(mapped), inputs.rigs, inputs.scale, options, inputs.priors)
    seconds = time.perf_counter() - t
    rec = result.reconstruction
    rotation = compare_to_ground_truth(rec, truth, "narrow")["relative_rotation_deg"]
    row = {"calibration": str(result.calibration), "held": sum(d.held for d in result.decisions),
           "rigs": len(result.decisions), "rotation_median_deg": rotation["median"],
           "rotation_max_deg": rotation["max"], "epipolar_p95_px": epipolar_p95(rec, truth), "seconds": seconds,
           "influential": vars(result.influential) if result.influential else None}
    if with_coverage:
        row["coverage"] = coverage(rec, truth, result.covariance or joint_covariance(result))
    logger.info("%s: %s", "after" if rule else "before", {k: v for k, v in row.items()})
    return row


def measure(name: str, mapped, truth, inputs, fixed_run: dict | None, both: bool, with_coverage: bool) -> dict:
    row: dict = {"network": name, "tracks": mapped.num_points3D(), "fixed_run": fixed_run}
    row["after"] = score(mapped, truth, inputs, AdjustOptions(), True, with_coverage)
    if both or (row["after"]["influential"] or {}).get("removed"):
        row["before"] = score(mapped, truth, inputs, AdjustOptions(), False, with_coverage)
    else:
        row["before"] = "same as after (nothing removed: the adjustment is main's, the score only computed)"
    fixed = score(mapped, truth, inputs, AdjustOptions(calibration=Calibration.FIXED), True, False)
    row["fixed_same_mapping"] = {k: fixed[k] for k in ("rotation_median_deg", "rotation_max_deg", "epipolar_p95_px")}
    return row


RULE = adjust_module.MAX_TRACK_INFLUENCE


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bench", type=Path, default=None)
    parser.add_argument("--networks", nargs="*", default=None)
    parser.add_argument("--hor", type=Path, default=None)
    parser.add_argument("--hor-scenes", nargs="*", default=None)
    parser.add_argument("--both", action="store_true", help="score the rule off even where it removed nothing")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(name)s %(levelname)s %(message)s")
    logger.setLevel(logging.INFO)
    logging.getLogger("rigsfm.run.adjustment.adjust").setLevel(logging.INFO)
    rows = json.loads(args.out.read_text())["rows"] if args.out.exists() else []
    done = {r["network"] for r in rows}
    if args.bench is not None:
        names = args.networks or FIRST + sorted(p.name for p in args.bench.iterdir()
                                               if (p / "default" / "mapping").is_dir() and p.name not in FIRST)
        for name, inputs, truth, mapped in default_mapping_models(args.bench, names, done):
            results = json.loads((args.bench / "results" / f"{name}.json").read_text())
            fixed = results.get("fixed") or {}
            fixed_run = {"rotation_max_deg": (fixed.get("rotation_deg") or {}).get("max"),
                         "rotation_median_deg": (fixed.get("rotation_deg") or {}).get("median"),
                         "epipolar_p95_px": fixed.get("true_epipolar_p95_px"),
                         "default_narrow_used": (results.get("default") or {}).get("narrow_used")}
            t = time.perf_counter()
            rows.append(measure(name, mapped, truth, inputs, fixed_run, args.both, True))
            print(f"{name}: {time.perf_counter() - t:.0f} s", flush=True)
            write_json_atomic(args.out, {"rows": rows}, overwrite=True)
    if args.hor is not None:
        for label, _, dataset, inputs, mapped in cached_mapping_models(args.hor, args.hor_scenes, done):
            t = time.perf_counter()
            rows.append(measure(label, mapped, dataset.load_ground_truth(), inputs, None, args.both, False))
            print(f"{label}: {time.perf_counter() - t:.0f} s", flush=True)
            write_json_atomic(args.out, {"rows": rows}, overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
