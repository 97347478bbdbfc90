"""GPU SIFT against the CPU's on one machine: the same rendered arena run with ``--device cuda`` and ``--device cpu``.

``python benchmarks/gpu.py OUT [--num-rigs N] [--image-scale S] [--devices cuda cpu]`` needs pycolmap's CUDA build
(``rigsfm[gpu]``) and a GPU; it renders the demo's arena into OUT/scene, runs rigsfm once per device into
OUT/run-DEVICE and writes OUT/gpu.json: per device the wall time, each stage's time, the model's size and the
narrow accuracy against the exact truth next to the fixed-calibration oracle. ``--device cpu`` on that machine is
the baseline: both rows come from the same machine and pycolmap build.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import pycolmap

from rigsfm.core.io import write_json_atomic
from rigsfm.run.matching.gpu import cuda_device_count
from rigsfm.run.options import MatchingOptions
from rigsfm.run.pipeline import RunOptions, run
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.demo import score
from rigsfm.synth.scene import SceneOptions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--num-rigs", type=int, default=8)
    parser.add_argument("--image-scale", type=float, default=1.0)
    parser.add_argument("--devices", nargs="+", default=["cuda", "cpu"], choices=["cuda", "cpu"])
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    report: dict = {"pycolmap": pycolmap.__version__, "has_cuda": bool(getattr(pycolmap, "has_cuda", False)),
                    "cuda_devices": cuda_device_count()}
    start = time.perf_counter()
    dataset = render_dataset(args.out / "scene", SceneOptions(num_rigs=args.num_rigs, image_scale=args.image_scale),
                             overwrite=True)
    report["render_s"] = time.perf_counter() - start
    for device in args.devices:
        start = time.perf_counter()
        result = run(dataset.images, dataset.rigs, args.out / f"run-{device}", dataset.scale,
                     RunOptions(matching=MatchingOptions(device=device), overwrite=True))
        wall = time.perf_counter() - start
        accuracy = score(result, dataset)
        report[device] = {"wall_s": wall, "timings_s": result.summary.timings_s,
                          "points": result.reconstruction.num_points3D(),
                          "narrow": accuracy["narrow"], "oracle_narrow": accuracy["oracle_narrow"]}
        rotation = accuracy["narrow"]["relative_rotation_deg"]
        print(f"{device}: {wall:.1f} s wall, features {result.summary.timings_s['features']:.2f} s, matching "
              f"{result.summary.timings_s['matching']:.2f} s, rotation {rotation['median']:.4f} / "
              f"{rotation['max']:.4f} deg", flush=True)
        write_json_atomic(args.out / "gpu.json", report)


if __name__ == "__main__":
    main()
