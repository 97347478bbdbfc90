"""Two rigs 60 degrees apart: the smallest network, where COLMAP's defaults reconstruct nothing.

Only two wide images exist, so every 3D point is a two-view track (which COLMAP ignores by default)
and the initial pair is the whole model. rigsfm allows two-view tracks for small networks; the
rangefinder distance between the two rigs makes the result metric.

    python workflows/two_rigs.py OUT [--arc-deg 60] [--mapper incremental|global] [--image-scale 1.0]
"""

import argparse
from pathlib import Path

from rigsfm.run.options import Mapper, MappingOptions
from rigsfm.run.pipeline import RunOptions
from rigsfm.synth.demo import run_demo
from rigsfm.synth.scene import SceneOptions


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--arc-deg", type=float, default=60.0)
    parser.add_argument("--mapper", type=Mapper, default=Mapper.INCREMENTAL)
    parser.add_argument("--image-scale", type=float, default=1.0)
    args = parser.parse_args(argv)

    scene = SceneOptions(num_rigs=2, arc_deg=args.arc_deg, image_scale=args.image_scale)
    result = run_demo(args.out, scene, RunOptions(mapping=MappingOptions(mapper=args.mapper)))
    registered = result.run.summary.registered
    narrow = result.accuracy["narrow"]
    print("registered: " + ", ".join(f"{sensor} {r.registered}/{r.total}" for sensor, r in registered.items()))
    print(f"narrow relative rotation error: {narrow['relative_rotation_deg']['max']:.4f} deg, "
          f"distance error: {narrow['distance_error_percent']['max']:.4f} %")
    return result.accuracy


if __name__ == "__main__":
    main()
