"""The narrow stage's CPU (``--narrow auto``'s second pass) on a rendered scene, its inputs captured once and the stage
rerun alone: per repeat the process's CPU seconds (the stage processes included) and a hash of what the stage gave.

    python benchmarks/narrow_stage_cost.py SCENE [--repeats 3] [--profile out.prof] [--in-process] [--recapture]

``SCENE``: a rendered scene (``benchmarks/narrow_observations.py``'s ``WORK/persons8c``). The first call runs
``rigsfm run`` (defaults) into ``SCENE_stage`` and keeps ``second_pass``'s inputs in ``SCENE_stage/inputs.pkl``;
later calls reuse them (``--recapture``: run again). ``--profile``: cProfile of the stage's first repeat by
process CPU time (``--in-process``: the second adjustment in this process,
so that it shows in the profile). The hash covers the heads' pairs (their pixels, to the bit), the record's counts
and the second adjustment's poses, calibration and points: two code versions giving one hash gave the same result.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import os
import pickle
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import yaml  # noqa: E402


def capture(scene: Path, out: Path) -> None:
    """``rigsfm run`` (defaults) on ``scene`` into ``out``, keeping ``second_pass``'s inputs."""
    import shutil

    import rigsfm.run.pipeline as pipeline
    from benchmarks.narrow_observations import dataset, floor_scale
    from rigsfm.run.options import RunOptions

    original = pipeline.second_pass

    def keeping(result, world, inputs, options, offsets=None, bands=None, progress=None):
        (out / "inputs.pkl").write_bytes(pickle.dumps(dict(result=result, world=world, inputs=inputs, options=options,
                                                           offsets=offsets, bands=bands)))
        return original(result, world, inputs, options, offsets, bands, progress)

    options = yaml.safe_load((scene / "scene.yaml").read_text(encoding="utf-8"))["options"]
    data = dataset(scene.parent, scene.name, float(options["image_scale"]), int(options["seed"]))
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pipeline.second_pass = keeping  # type: ignore[assignment]
    try:
        pipeline.run(data.images, data.rigs, out / "run", floor_scale(data), RunOptions())
    finally:
        pipeline.second_pass = original  # type: ignore[assignment]


def fingerprint(result, record) -> str:
    """A hash of what the stage gave (module docstring)."""
    digest = hashlib.sha256()
    for pairs in (record.pairs, record.head_check_pairs or []):
        for p in pairs:
            digest.update(f"{p.frame}{p.i}{p.j}".encode())
            digest.update(np.ascontiguousarray(p.xy_i, dtype=np.float64).tobytes())
            digest.update(np.ascontiguousarray(p.xy_j, dtype=np.float64).tobytes())
    digest.update(json.dumps([record.used, record.head_persons, record.head_candidates, record.head_sigma_px,
                              record.points_added, record.observations_added], default=str).encode())
    rec = result.reconstruction
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        digest.update(np.asarray(image.cam_from_world().matrix(), dtype=np.float64).tobytes())
    for camera_id in sorted(rec.cameras):
        digest.update(np.asarray(rec.cameras[camera_id].params, dtype=np.float64).tobytes())
    for point_id in sorted(rec.points3D):
        digest.update(np.asarray(rec.points3D[point_id].xyz, dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", type=Path, default=None)
    parser.add_argument("--in-process", action="store_true")
    parser.add_argument("--recapture", action="store_true")
    args = parser.parse_args()
    out = args.scene.parent / f"{args.scene.name}_stage"
    if args.recapture or not (out / "inputs.pkl").exists():
        capture(args.scene, out)
    if args.in_process:
        from rigsfm.core.processes import IN_PROCESS_ENV
        os.environ[IN_PROCESS_ENV] = "1"
    from rigsfm.core.processes import stage_cpu_seconds
    from rigsfm.run.narrow.stage import second_pass

    kept = pickle.loads((out / "inputs.pkl").read_bytes())
    for repeat in range(args.repeats):
        profile = cProfile.Profile(time.process_time) if args.profile and repeat == 0 else None
        cpu, wall = stage_cpu_seconds(), time.perf_counter()
        if profile:
            profile.enable()
        result, record = second_pass(kept["result"], kept["world"], kept["inputs"], kept["options"], kept["offsets"],
                                     kept["bands"])
        if profile:
            profile.disable()
            profile.dump_stats(str(args.profile))
        cpu, wall = stage_cpu_seconds() - cpu, time.perf_counter() - wall
        print(json.dumps(dict(repeat=repeat, cpu_s=round(cpu, 2), wall_s=round(wall, 2), persons=record.head_persons,
                              hash=fingerprint(result, record))), flush=True)


if __name__ == "__main__":
    main()
