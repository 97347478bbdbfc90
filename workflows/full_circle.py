"""Full circle: 8 hybrid rigs around a homogeneous arena, reconstructed and scored against ground truth.

Renders the built-in synthetic arena (1624x1234 sensors, ~4 mm wide and ~16 mm narrow lenses, 6 cm rig
baselines, realistic calibration errors and a rangefinder distance), runs the whole pipeline with the
incremental mapper, and prints the narrow cameras' accuracy next to the oracle (the fixed-calibration
adjustment from the true poses: a reference, which the refined calibration can beat).

    python workflows/full_circle.py OUT [--num-rigs 8] [--image-scale 1.0]
"""

import argparse
import json
from pathlib import Path

from rigsfm.synth.demo import run_demo
from rigsfm.synth.scene import SceneOptions


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--num-rigs", type=int, default=8)
    parser.add_argument("--image-scale", type=float, default=1.0)
    args = parser.parse_args(argv)

    result = run_demo(args.out, SceneOptions(num_rigs=args.num_rigs, image_scale=args.image_scale))
    narrow, limit = result.accuracy["narrow"], result.accuracy["oracle_narrow"]
    print(f"narrow cameras registered: {narrow['registered']}/{narrow['total']}")
    print(f"pairwise rotation error (deg), median/max: {narrow['relative_rotation_deg']['median']:.4f} / "
          f"{narrow['relative_rotation_deg']['max']:.4f}  (oracle {limit['relative_rotation_deg']['max']:.4f})")
    print(f"narrow poses: {result.run.workspace.narrow_poses}")
    return json.loads((args.out / "accuracy.json").read_text())


if __name__ == "__main__":
    main()
