"""``--narrow auto|on|off`` (narrow observations after a first adjustment) against the truth, scene by scene.

    python benchmarks/narrow_observations.py WORK [--scenes flat8 persons8 plain8] [--image-scale 0.5]
        [--modes off auto] [--out results.json] [--frames-per-rig 2 --frame-period-s 0.1 --frame-offsets rig03=1]

Scenes (rendered into ``WORK/<scene>``, reused when there; realistic calibration error in rigs.yaml, one frame):
``flat8``: 8 rigs round a crowd texture painted on the floor (``--textured-centre``); ``persons8``: 8 rigs round
3D persons (4 per m2, heads at 1.5-1.9 m, occluding bodies; rigsfm.synth.persons); ``plain8``: 8 rigs round the
homogeneous centre (featureless narrow views); ``flat4`` / ``persons4``: the same with 4 rigs on a 135 deg arc.
``--frames-per-rig``, ``--frame-period-s``, ``--frame-offsets``: a recording instead of one frame, its rigs
shifted in time by the offsets (the persons walk meanwhile; rigsfm.synth's options).

Each mode runs ``rigsfm.run.pipeline.run`` into ``WORK/<scene>_<mode>`` (fresh). Per run: wall time, CPU seconds (all stages; steadier than the wall time on a shared machine), narrow
relative-rotation error median / max (deg, every narrow pair against the exact ground truth), the worst pair's
95th percentile of the true epipolar distance (px; true floor points, ``benchmarks/hold_or_refine.epipolar_p95``),
the median 95 % band (px), the self-check's verdicts, and with narrow observations what ``--narrow`` decided, the
matches added and the held-out check's verdicts. benchmarks/README.md ("Narrow observations") holds the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from rigsfm.run.options import NarrowMode, RunOptions  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

SCENES = {
    "flat8": dict(num_rigs=8, textured_centre=True),
    "persons8": dict(num_rigs=8, persons_per_m2=4.0),
    "plain8": dict(num_rigs=8),
    "flat4": dict(num_rigs=4, arc_deg=135.0, textured_centre=True),
    "persons4": dict(num_rigs=4, arc_deg=135.0, persons_per_m2=4.0),
    # the narrow cameras aimed at the crowd's centre (as benchmarks/associate.py's crowds): heads seen by several
    # narrow views; persons8's narrow views, aimed 14 deg lower, share no head
    "persons8c": dict(num_rigs=8, persons_per_m2=4.0, narrow_extra_pitch_deg=-4.0),
}


def dataset(work: Path, name: str, image_scale: float, seed: int, recording: dict | None = None):
    """``recording``: SceneOptions' frames_per_rig, frame_period_s and frame_offsets (an unsynchronised recording)."""
    from rigsfm.synth.dataset import SyntheticDataset, render_dataset

    options = SceneOptions(image_scale=image_scale, seed=seed, **SCENES[name],  # type: ignore[arg-type]
                           **(recording or {}))
    root = work / name
    if (root / "scene.yaml").exists():
        # A scene rendered before is reused only with its own options: floor_scale and the truth read them.
        recorded = yaml.safe_load((root / "scene.yaml").read_text(encoding="utf-8"))["options"]
        wanted = yaml.safe_load(yaml.safe_dump(dataclasses.asdict(options)))
        differ = [f"{key} {recorded.get(key)!r} (asked {value!r})" for key, value in wanted.items()
                  if recorded.get(key) != value]
        if differ:
            raise SystemExit(f"{root} was rendered with other options: {', '.join(differ)}; pass those "
                             "(--seed, --image-scale, the recording's) or another WORK")
        return SyntheticDataset(root, root / "images", root / "rigs.yaml", root / "rigs_exact.yaml",
                                root / "scale.yaml", root / "ground_truth", options, ())
    return render_dataset(root, options)


def floor_scale(data) -> Path:
    """The scene's scale.yaml, or one with the floor bar's end points (rigsfm.synth.dataset.scale_with_floor_bar)."""
    from rigsfm.synth.dataset import scale_with_floor_bar

    return scale_with_floor_bar(data, Path(data.root) / "scale_floor_bar.yaml")


def verdicts(pairs: list[dict]) -> dict:
    counts: dict[str, int] = {}
    for p in pairs:
        counts[p["verdict"]] = counts.get(p["verdict"], 0) + 1
    return counts


def measure(data, out: Path, mode: NarrowMode) -> dict:
    import pycolmap

    from benchmarks.hold_or_refine import epipolar_p95
    from rigsfm.run.pipeline import run
    from rigsfm.synth.truth import compare_to_ground_truth

    shutil.rmtree(out, ignore_errors=True)
    scale = floor_scale(data)  # builds the arena (seconds): not the run's time
    start = time.perf_counter()
    result = run(data.images, data.rigs, out, scale, RunOptions(narrow=mode))
    seconds = time.perf_counter() - start
    truth = pycolmap.Reconstruction(str(data.ground_truth))
    narrow = compare_to_ground_truth(result.reconstruction, truth, "narrow")
    summary = json.loads(result.workspace.summary.read_text(encoding="utf-8"))
    bands = [p["band_px"] for p in (summary.get("uncertainty") or {}).get("pairs", []) if p.get("band_px") is not None]
    record = summary.get("narrow_observations") or {}
    return {
        "mode": str(mode), "seconds": round(seconds, 1), "cpu_s": round(sum(summary["cpu_s"].values()), 1),
        "rotation_deg": {k: round(narrow["relative_rotation_deg"][k], 4) for k in ("median", "max")},
        "true_epipolar_p95_px": epipolar_p95(result.reconstruction, truth),
        "band_median_px": float(np.median(bands)) if bands else None,
        "self_check": verdicts((summary.get("epipolar_self_check") or {}).get("pairs", [])),
        "narrow_used": record.get("used"), "narrow_reason": record.get("reason"),
        "narrow_observations": record.get("observations_added"), "held_out": record.get("held_out_matches"),
        "held_out_check": verdicts(record.get("held_out_check") or []),
        "matched_by": record.get("matched_by"), "head_persons": record.get("head_persons"),
        "head_verdicts": record.get("head_verdicts"),
        "stages_s": summary["timings_s"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--scenes", nargs="+", default=["flat8", "persons8", "plain8"], choices=sorted(SCENES))
    parser.add_argument("--modes", nargs="+", default=["off", "auto"], choices=[str(m) for m in NarrowMode])
    parser.add_argument("--image-scale", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--frames-per-rig", type=int, default=1)
    parser.add_argument("--frame-period-s", type=float, default=0.5)
    parser.add_argument("--frame-offsets", default="", help="rig03=1,rig05=-0.5: unsynchronised rigs (frames)")
    args = parser.parse_args()
    offsets = tuple((rig, float(value)) for rig, value in
                    (item.split("=") for item in args.frame_offsets.split(",") if item))
    recording = dict(frames_per_rig=args.frames_per_rig, frame_period_s=args.frame_period_s, frame_offsets=offsets)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    rows = []
    for name in args.scenes:
        data = dataset(args.work, name, args.image_scale, args.seed, recording)
        for mode in args.modes:
            row = {"scene": name, **measure(data, args.work / f"{name}_{mode}", NarrowMode(mode))}
            print(json.dumps(row), flush=True)
            rows.append(row)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
