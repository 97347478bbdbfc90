"""(benchmarks/README.md, "The floor's uncertainty on floors of sparse points", 2026-11-28) Render and run networks
without a crowd, whose floor rests on the sparse points of the textured ground (``plain``: a featureless centre;
``flat``: a texture painted on the centre too) and the scene's known-length bar, with the default ``RunOptions``.

    PYTHONPATH=. python benchmarks/floor_sigma_sparse.py OUT NAME ...   (NAME: one of ``NETWORKS``)

OUT/NAME/scene (rendered once, ``image_scale`` 0.5, its own scale.yaml: the camera distance and the 2 m bar on the
textured ground), OUT/NAME/run. Score with ``benchmarks/floor_sigma_measure.py OUT/NAME ...``.
"""
import sys
import time
from pathlib import Path

from rigsfm.run.pipeline import RunOptions, run
from rigsfm.synth.dataset import render_dataset
from rigsfm.synth.scene import SceneOptions


def _net(num_rigs: int, arc_deg: float, seed: int, flat: bool) -> SceneOptions:
    return SceneOptions(num_rigs=num_rigs, arc_deg=arc_deg, seed=seed, textured_centre=flat, image_scale=0.5)


NETWORKS = {  # benchmarks/networks.py's plain and flat networks of 4 rigs or more, and three more seeds and arcs
    "plain4_360_s0": _net(4, 360, 0, False), "flat4_135_s0": _net(4, 135, 0, True),
    "plain6_180_s1": _net(6, 180, 1, False), "flat6_360_s1": _net(6, 360, 1, True),
    "plain8_360_s0": _net(8, 360, 0, False), "flat8_360_s0": _net(8, 360, 0, True),
    "plain8_360_s3": _net(8, 360, 3, False), "plain4_180_s2": _net(4, 180, 2, False),
    "plain8_240_s4": _net(8, 240, 4, False), "flat8_360_s5": _net(8, 360, 5, True),
    "flat4_360_s2": _net(4, 360, 2, True), "flat6_180_s3": _net(6, 180, 3, True), "flat8_120_s7": _net(8, 120, 7, True),
}

if __name__ == "__main__":
    out = Path(sys.argv[1])
    for name in sys.argv[2:]:
        root = out / name
        start = time.perf_counter()
        if not (root / "scene" / "ground_truth").is_dir():
            render_dataset(root / "scene", NETWORKS[name], overwrite=True)
        rendered = time.perf_counter()
        run(root / "scene" / "images", root / "scene" / "rigs.yaml", root / "run", root / "scene" / "scale.yaml",
            RunOptions(overwrite=True))
        print(f"{name}: rendered in {rendered - start:.0f} s, run in {time.perf_counter() - rendered:.0f} s", flush=True)
