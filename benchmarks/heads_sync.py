"""The frame-offset check of run's own heads (rigsfm.run.narrow.timing) on a finished run's model.

    python benchmarks/heads_sync.py OUT IMAGES [--json FILE] [--no-carry]
    python benchmarks/heads_sync.py --score OUT GROUND_TRUTH RIG  # a run's narrow rotation on RIG's pairs

OUT: a ``rigsfm run`` workspace of a recording (e.g. benchmarks/narrow_observations.py's ``WORK/persons8c_off``:
the first adjustment, delivered in the floor frame); IMAGES: its images. Prints each rig's counts per shift, its
named offset and z, and the check's CPU seconds. benchmarks/README.md ("Frame offsets from run's own heads") holds
the table.
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

from rigsfm.associate.sync import Correction  # noqa: E402
from rigsfm.core.blas_threads import one_blas_thread  # noqa: E402
from rigsfm.core.workspace import Workspace  # noqa: E402
from rigsfm.run.narrow.timing import time_heads  # noqa: E402


def score(out: Path, truth_dir: Path, rig: str) -> dict:
    """Narrow relative-rotation error (deg) against the exact truth, one pair per two narrow cameras (the rigs are
    static: their first shared frame): the median and max over all pairs, over RIG's pairs and over the others."""
    import itertools

    import numpy as np

    from rigsfm.core.conventions import rotation_angle_deg
    from rigsfm.core.names import name_of

    estimate, truth = pycolmap.Reconstruction(str(Workspace(out).sparse)), pycolmap.Reconstruction(str(truth_dir))
    first: dict[str, pycolmap.Image] = {}
    for image in sorted(estimate.images.values(), key=lambda im: name_of(im).frame):
        if image.has_pose and name_of(image).is_narrow:
            first.setdefault(name_of(image).camera, image)
    errors: dict[str, list[float]] = {"all": [], "rig": [], "others": []}
    for a, b in itertools.combinations(sorted(first), 2):
        ia, ib = first[a], first[b]
        ga, gb = truth.find_image_with_name(ia.name), truth.find_image_with_name(ib.name)
        e = ib.cam_from_world() * ia.cam_from_world().inverse()
        g = gb.cam_from_world() * ga.cam_from_world().inverse()
        error = rotation_angle_deg(e.rotation.matrix(), g.rotation.matrix())
        errors["all"].append(error)
        errors["rig" if rig in (a.split("/")[0], b.split("/")[0]) else "others"].append(error)
    return {k: {"median": round(float(np.median(v)), 4), "max": round(float(np.max(v)), 4), "pairs": len(v)}
            for k, v in errors.items() if v}


def main() -> None:
    if sys.argv[1:2] == ["--score"]:
        print(json.dumps(score(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4])))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("images", type=Path)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--correct", default=Correction.CONFIRM, choices=list(Correction), type=Correction,
                        help="the views' pose correction: each association's own, carried from the frame before, carried but the tested camera's, none")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    workspace = Workspace(args.out)
    model = pycolmap.Reconstruction(str(workspace.sparse))
    poses = json.loads(workspace.narrow_poses.read_text(encoding="utf-8"))
    bands = {(p["i"], p["j"]): p["epipolar_band_95_px"] for p in poses.get("pairs", [])
             if p.get("epipolar_band_95_px") is not None}
    cpu = time.process_time()
    with one_blas_thread():
        check = time_heads(model, args.images, bands, correct=args.correct)
    record = {**check.to_dict(), "correct": str(args.correct), "cpu_s": round(time.process_time() - cpu, 1)}
    print(json.dumps(record), flush=True)
    if args.json:
        args.json.write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
