"""The run's head candidates (``rigsfm.run.narrow.heads.detect_heads``) against the rendered truth.

    python benchmarks/head_candidates.py DATASET RUN [--frame frame0000] [--within 3] [--visible 0.5]

DATASET: a rendered crowd of 3D persons (``persons/heads.csv``: every head centre per image, with its visible
fraction); RUN: a ``rigsfm run`` output on it (``sparse/``: the delivered model, in the floor frame). Per narrow
image of ``--frame``: the CPU seconds of the detection, the true heads at least ``--visible`` visible, how many of
them a candidate lies within ``--within`` px of (recall), and how many candidates lie that close to one
(precision).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from rigsfm.core.image_files import read_image  # noqa: E402
from rigsfm.run.narrow.heads import detect_heads, scene_footprint  # noqa: E402


def true_heads(dataset: Path, visible: float) -> dict[str, np.ndarray]:
    """image -> N x 2 true head centres (COLMAP pixels) at least ``visible`` visible."""
    heads: dict[str, list] = {}
    with open(dataset / "persons" / "heads.csv", newline="") as f:
        for row in csv.DictReader(f):
            if float(row["visible_fraction"]) >= visible:
                heads.setdefault(row["image"], []).append((float(row["x"]), float(row["y"])))
    return {name: np.asarray(rows, dtype=np.float64) for name, rows in heads.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--frame", default="frame0000")
    parser.add_argument("--within", type=float, default=3.0)
    parser.add_argument("--visible", type=float, default=0.5)
    args = parser.parse_args()
    model = pycolmap.Reconstruction(str(args.run / "sparse"))
    truth = true_heads(args.dataset, args.visible)
    footprint = scene_footprint(model)  # as match_heads gives it
    totals = np.zeros(4)  # CPU s, true heads found, true heads, candidates near a true head
    count = 0
    print("| image | CPU (s) | candidates | recall | precision |")
    print("| --- | --- | --- | --- | --- |")
    for image in sorted(model.images.values(), key=lambda im: im.name):
        if "/narrow/" not in image.name or args.frame not in image.name:
            continue
        gray = read_image(args.dataset / "images" / image.name, cv2.IMREAD_GRAYSCALE)
        start = time.process_time()
        found = detect_heads(image, gray, footprint)
        cpu = time.process_time() - start
        known = truth.get(image.name, np.zeros((0, 2)))
        recalled = near = 0
        if len(found) and len(known):
            recalled = int(np.sum(cKDTree(found[:, :2]).query(known)[0] < args.within))
            near = int(np.sum(cKDTree(known).query(found[:, :2])[0] < args.within))
        totals += (cpu, recalled, len(known), near)
        count += len(found)
        print(f"| {image.name} | {cpu:.2f} | {len(found)} | {recalled / max(len(known), 1):.3f} "
              f"| {near / max(len(found), 1):.3f} |")
    print(f"| all | {totals[0]:.1f} | {count} | {totals[1] / max(totals[2], 1):.3f} | {totals[3] / max(count, 1):.3f} |")


if __name__ == "__main__":
    main()
