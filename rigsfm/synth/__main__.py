"""``python -m rigsfm.synth OUT [--num-rigs N] [--arc-deg A] [--image-scale S] [--seed K]``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from rigsfm.core.errors import RigsfmError
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.persons import parse_frame_offsets
from rigsfm.synth.scene import SceneOptions

logger = logging.getLogger("rigsfm.synth")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rigsfm.synth", description=__doc__)
    parser.add_argument(
        "out", type=Path, help="output folder (images/, rigs.yaml, scale.yaml, ground_truth/)"
    )
    parser.add_argument("--num-rigs", type=int, default=8)
    parser.add_argument(
        "--arc-deg", type=float, default=360.0, help="angular span of the rigs (360 = circle)"
    )
    parser.add_argument("--image-scale", type=float, default=1.0, help="0.5 -> 812x617 images")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--radius", type=float, default=15.0, help="rig circle radius (m)")
    parser.add_argument("--rig-height", type=float, default=3.5,
                        help="mean wide-camera height (m); e.g. --radius 20 --rig-height 8 sees a crowd from 15-30 m")
    parser.add_argument("--frames-per-rig", type=int, default=1)
    parser.add_argument("--textured-centre", action="store_true", help="crowd-like centre instead of uniform")
    parser.add_argument("--persons-per-m2", type=float, default=0.0,
                        help="3D persons standing and walking on the centre disc (e.g. 4); 0: none")
    parser.add_argument("--narrow-pitch-deg", type=float, default=10.0,
                        help="how much further down than its wide camera each narrow camera looks; -4 aims the "
                             "narrow views at the crowd's centre, so that they share persons (for `rigsfm associate`)")
    parser.add_argument("--frame-period-s", type=float, default=0.5, help="time between a rig's frames")
    parser.add_argument("--frame-offsets", default="",
                        help="unsynchronised rigs: rig02=1,rig05=-0.5 takes rig02's frame k at time k+1 and rig05's at "
                             "k-0.5 (frames; fractions too: the persons walk continuously)")
    parser.add_argument("--exposure-jitter", type=float, default=0.0,
                        help="each image's exposure gain uniform in 1 +- this (e.g. 0.15)")
    parser.add_argument("--jpeg-quality", type=int, default=0, help="write JPEG images of this quality (1..100)")
    parser.add_argument("--no-calibration-noise", action="store_true", help="rigs.yaml = exact calibration")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset in OUT")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        options = SceneOptions(
            num_rigs=args.num_rigs,
            arc_deg=args.arc_deg,
            image_scale=args.image_scale,
            seed=args.seed,
            radius=args.radius,
            rig_height=args.rig_height,
            frames_per_rig=args.frames_per_rig,
            textured_centre=args.textured_centre,
            calibration_noise=not args.no_calibration_noise,
            persons_per_m2=args.persons_per_m2,
            narrow_extra_pitch_deg=args.narrow_pitch_deg,
            frame_period_s=args.frame_period_s,
            frame_offsets=parse_frame_offsets(args.frame_offsets),
            exposure_jitter=args.exposure_jitter,
            jpeg_quality=args.jpeg_quality,
        )
        dataset = render_dataset(args.out, options, overwrite=args.overwrite)
    except (ValueError, RigsfmError) as e:
        logger.error("%s", e)
        return 2
    logger.info("dataset ready: %s (%d images)", dataset.root, len(dataset.image_names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
