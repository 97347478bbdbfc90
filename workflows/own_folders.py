"""A run on your own folders, through the library API, and how to read the result.

Your images:   IMAGES/<rig>/wide/<frame>.png and IMAGES/<rig>/narrow/<frame>.png
Your rigs:     rigs.yaml (intrinsics in COLMAP's pixel convention, narrow_from_wide in metres)
Your scale:    scale.yaml (optional: a rangefinder distance or an object of known length)

    python workflows/own_folders.py IMAGES rigs.yaml OUT [--scale scale.yaml] [--overwrite]

It prints each narrow pair's relative pose in the paper's format and the fundamental matrix you need
to search correspondences along epipolar lines.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from rigsfm.run.pipeline import RunOptions, run


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("images", type=Path)
    parser.add_argument("rigs", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--scale", type=Path, default=None)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)

    result = run(args.images, args.rigs, args.out, args.scale, RunOptions(overwrite=args.overwrite))
    poses = json.loads(result.workspace.narrow_poses.read_text())
    unit = "m" if poses["metric"] else "units (NOT metric)"
    for pair in poses["pairs"]:
        e = pair["euler_zyx_deg"]
        distance = pair.get("distance_m", pair.get("distance_units"))
        print(f"{pair['i']} -> {pair['j']}: yaw {e['yaw']:+.3f} pitch {e['pitch']:+.3f} roll {e['roll']:+.3f} deg,"
              f" direction {np.round(pair['centre_direction_in_i'], 4).tolist()}, distance {distance:.3f} {unit}")
        print(f"  F_ji = {np.array2string(np.array(pair['F_ji']), precision=6)}")
    for warning in result.summary.warnings:
        print(f"warning: {warning}")
    return poses


if __name__ == "__main__":
    main()
