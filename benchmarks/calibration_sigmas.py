"""Are the uncertainties ``rigsfm calibrate`` writes into rigs.yaml honest? Errors / sigmas over many boards.

    python benchmarks/calibration_sigmas.py [--seeds 24] [--first 0] [--work DIR] [--out results.json]

Per seed: ChArUco board views of the synthetic 960x720 hybrid rig (``rigsfm.synth.boards``, exact
ground truth) rendered, calibrated with ``calibrate_rigs`` and written with ``write_calibration``; the
rigs.yaml is read back (``load_rigs``, ``load_sigmas``) and every written parameter's actual error is divided
by its written sigma. The setups cycle with the seed over 24 / 16 / 12 views that both cameras see (plus 8
wide-only views towards the image borders) and a 4:1 / 3:1 focal ratio. Per parameter group (focal, principal
point, distortion per camera; E^sl rotation, translation) the RMS of error / sigma should be ~1: below 0.7
the sigmas are pessimistic, above 1.4 they are overconfident. Rotation errors are w = Log(R_true R^T), the
convention of the written sigmas (R_true = Exp(w) R). Renders are kept in ``--work`` (default: a temporary
folder) and reused.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from rigsfm.calibrate import calibrate_rigs, write_calibration
from rigsfm.calibrate.board import board_spec_from_dict
from rigsfm.calibrate.intrinsics import colmap_camera
from rigsfm.calibrate.uncertainty import load_sigmas
from rigsfm.core.rig import load_rigs
from rigsfm.synth.boards import HybridRig, board_views, default_hybrid_rig, write_board_dataset

BOARD = {"type": "charuco", "squares": [11, 8], "square": 0.06, "marker": 0.045, "dictionary": "DICT_5X5_100"}
SETUPS = [(24, 4.0), (16, 4.0), (12, 4.0), (24, 3.0), (16, 3.0), (12, 3.0)]  # (stereo views, focal ratio)
WIDE_ONLY_VIEWS = 8
GROUPS = {"focal": slice(0, 2), "principal point": slice(2, 4), "distortion": slice(4, None)}
HONEST = (0.7, 1.4)


@dataclass
class Calibration:
    """One seed's calibration: per group, actual errors and written sigmas (written units)."""

    seed: int
    stereo_views: int
    ratio: float
    seconds: float
    inflation: tuple[float, float, float]  # the joint refinement's sigma factors (wide, narrow, E^sl)
    errors: dict[str, list[float]]
    sigmas: dict[str, list[float]]


def setup(seed: int) -> tuple[int, float, HybridRig]:
    stereo, ratio = SETUPS[seed % len(SETUPS)]
    return stereo, ratio, default_hybrid_rig(ratio=ratio)


def render(seed: int, work: Path) -> Path:
    """``work/seed_NN/BOARD`` (rendered once; ~10-30 s on the 2-core machine)."""
    root = work / f"seed_{seed:02d}"
    if not (root / "done").is_file():
        shutil.rmtree(root, ignore_errors=True)
        stereo, _, rig = setup(seed)
        poses = board_views(np.random.default_rng(1000 + seed), stereo, WIDE_ONLY_VIEWS)
        write_board_dataset(root / "BOARD", "rig01", board_spec_from_dict(BOARD), rig, poses, seed=seed)
        (root / "done").write_text("")
    return root / "BOARD"


def calibrate_and_compare(seed: int, work: Path) -> Calibration:
    board_dir = render(seed, work)
    stereo, ratio, rig = setup(seed)
    start = time.perf_counter()
    result = calibrate_rigs(board_dir, board_spec_from_dict(BOARD))
    seconds = time.perf_counter() - start
    out = work / f"seed_{seed:02d}" / "rigs.yaml"
    write_calibration(result, out, overwrite=True)
    (written,) = load_rigs(out)
    sigmas = load_sigmas(out)["rig01"]
    errors: dict[str, list[float]] = {}
    sig: dict[str, list[float]] = {}
    for sensor, truth in (("wide", rig.wide), ("narrow", rig.narrow)):
        camera = written.camera(sensor)
        true = colmap_camera(truth.K, truth.dist, truth.size, camera.model.name).params
        s = sigmas.sensor(sensor)
        if s is None:
            raise RuntimeError(f"seed {seed}: no sigmas written for the {sensor} camera")
        for group, cut in GROUPS.items():
            held = s[cut] == 0  # FULL_OPENCV's k4..k6: not estimated
            errors[f"{sensor} {group}"] = list((np.asarray(camera.params)[cut] - true[cut])[~held])
            sig[f"{sensor} {group}"] = list(s[cut][~held])
    R = written.narrow_from_wide.rotation.matrix()
    w = Rotation.from_matrix(rig.R @ R.T).as_rotvec()  # not cv2.Rodrigues: it gives 0 below 1e-5 rad
    errors["E^sl rotation"] = list(np.degrees(w))
    sig["E^sl rotation"] = list(sigmas.rotation_deg)
    errors["E^sl translation"] = list(rig.t - np.asarray(written.narrow_from_wide.translation))
    sig["E^sl translation"] = list(sigmas.translation_m)
    inflation = result.rigs[0].stereo.joint_detail.inflation
    return Calibration(seed, stereo, ratio, seconds, inflation, errors, sig)


def summary(runs: list[Calibration]) -> dict[str, dict[str, float]]:
    """Per group: RMS(error / sigma), its count, the largest |error / sigma|, RMS error and RMS sigma."""
    out = {}
    for group in runs[0].errors:
        e = np.concatenate([r.errors[group] for r in runs])
        s = np.concatenate([r.sigmas[group] for r in runs])
        z = e / s
        out[group] = {"rms_z": float(np.sqrt(np.mean(z ** 2))), "n": len(z), "max_abs_z": float(np.abs(z).max()),
                      "rms_error": float(np.sqrt(np.mean(e ** 2))), "rms_sigma": float(np.sqrt(np.mean(s ** 2)))}
    return out


UNITS = {"focal": ("px", 1.0), "principal point": ("px", 1.0), "distortion": ("", 1.0), "rotation": ("deg", 1.0),
         "translation": ("mm", 1000.0)}


def table(runs: list[Calibration]) -> str:
    header = (f"{'group':<26} {'n':>4} {'RMS err/sigma':>14} {'max |z|':>8} {'RMS error':>11} {'RMS sigma':>11}"
              "  unit")
    title = f"{len(runs)} calibrations (seeds {runs[0].seed}..{runs[-1].seed}), honest if {HONEST[0]} <= RMS <= {HONEST[1]}"
    lines = [title, "", header]
    for group, row in summary(runs).items():
        unit, factor = next(v for k, v in UNITS.items() if k in group)
        flag = "" if HONEST[0] <= row["rms_z"] <= HONEST[1] else "   <-- not honest"
        lines.append(f"{group:<26} {row['n']:>4} {row['rms_z']:>14.2f} {row['max_abs_z']:>8.2f} "
                     f"{factor * row['rms_error']:>11.4g} {factor * row['rms_sigma']:>11.4g}  {unit}{flag}")
    lines.append("")
    lines.append("per setup (stereo views, focal ratio): RMS err/sigma of each group in the order above")
    for stereo, ratio in SETUPS:
        mine = [r for r in runs if (r.stereo_views, r.ratio) == (stereo, ratio)]
        if mine:
            lines.append(f"  {stereo:>2} views, {ratio:g}:1 ({len(mine)} seeds): "
                         + " ".join(f"{row['rms_z']:.2f}" for row in summary(mine).values()))
    inflation = np.array([r.inflation for r in runs])
    lines.append("sigma inflation from the jackknife (wide / narrow / E^sl): median "
                 + " / ".join(f"{v:.2f}" for v in np.median(inflation, 0)) + ", max "
                 + " / ".join(f"{v:.2f}" for v in inflation.max(0)))
    lines.append(f"calibration time per seed: median {np.median([r.seconds for r in runs]):.1f} s")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=24)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None, help="keep the renders here (reused if present)")
    parser.add_argument("--out", type=Path, default=None, help="write every error and sigma as JSON")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        runs = []
        for seed in range(args.first, args.first + args.seeds):
            runs.append(calibrate_and_compare(seed, work))
            print(f"seed {seed}: {runs[-1].stereo_views} stereo views, {runs[-1].ratio:g}:1, "
                  f"{runs[-1].seconds:.1f} s", flush=True)
        print()
        print(table(runs))
        print(f"total {time.perf_counter() - start:.0f} s (rendering included)")
    if args.out:
        args.out.write_text(json.dumps({"summary": summary(runs), "runs": [r.__dict__ for r in runs]}, indent=1,
                                       default=float))


if __name__ == "__main__":
    main()
