"""Throughput of `rigsfm track`: frames per second, local process pool vs a local Ray instance.

    python benchmarks/track_throughput.py [--rigs 3] [--frames 8] [--workers 2] [--image-scale 0.5]

Renders a small arena, runs `rigsfm run` for the reference, renders a recording with shake, then tracks
it twice into separate copies of the workspace: with the local pool and with Ray (``num_cpus=workers``).
Prints one JSON line. Ray's start-up is reported apart from its frames per second. Timings on a shared
machine are noisy.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rigs", type=int, default=3)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--image-scale", type=float, default=0.5)
    args = parser.parse_args()

    from rigsfm.run.pipeline import RunOptions, run
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.motion import render_recording, shaken_motions
    from rigsfm.synth.scene import SceneOptions
    from rigsfm.track import Executor, TrackOptions, track

    with tempfile.TemporaryDirectory(prefix="rigsfm-track-bench-") as tmp:
        root = Path(tmp)
        scene = SceneOptions(num_rigs=args.rigs, arc_deg=min(360.0, 60.0 * args.rigs), image_scale=args.image_scale,
                             seed=1)
        dataset = render_dataset(root / "scene", scene)
        run(dataset.images, dataset.rigs, root / "out", dataset.scale, RunOptions())
        rng = np.random.default_rng(0)
        motions = {f"rig{i + 1:02d}": shaken_motions(args.frames, rng, (0.02, 0.05), (1.0, 4.0))
                   for i in range(args.rigs)}
        recording = render_recording(root / "new", scene, motions)
        frames = args.rigs * args.frames
        results = {"benchmark": "track_throughput", "rigs": args.rigs, "frames": frames,
                   "image_scale": args.image_scale, "workers": args.workers}

        shutil.copytree(root / "out", root / "out_local")
        start = time.perf_counter()
        local = track(root / "out_local", recording.images, TrackOptions(executor=Executor.LOCAL, workers=args.workers))
        seconds = time.perf_counter() - start
        results["local_s"] = round(seconds, 2)
        results["local_fps"] = round(frames / seconds, 3)
        per_frame = [f["time_s"] for r in local.poses["rigs"].values() for f in r["frames"]]
        results["per_frame_s_median"] = round(float(np.median(per_frame)), 3)

        import ray

        shutil.copytree(root / "out", root / "out_ray")
        start = time.perf_counter()
        ray.init(num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
        results["ray_startup_s"] = round(time.perf_counter() - start, 2)
        try:
            start = time.perf_counter()
            track(root / "out_ray", recording.images, TrackOptions(executor=Executor.RAY))
            seconds = time.perf_counter() - start
        finally:
            ray.shutdown()
        results["ray_s"] = round(seconds, 2)
        results["ray_fps"] = round(frames / seconds, 3)
        results["ray_fps_with_startup"] = round(frames / (seconds + results["ray_startup_s"]), 3)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
