"""(benchmarks/README.md, "The floor's uncertainty made honest", 2026-11-28) Render and run the 8-rig crowds the floor's
sigmas are scored on, and keep beside each run what the code before the refit delivered.

    PYTHONPATH=. python benchmarks/floor_sigma_runs.py OUT 1 2 2:off 3 ...   (SEED or SEED:off for --narrow off)

OUT/r8sSEED/scene (rendered once per seed, as workflows/crowd.py does), OUT/r8sSEED[_off]/run (this code), and
OUT/r8sSEED[_off]_old/run: the same model moved into the first floor fit's frame, with the scatter-only sigmas as the
reported ones (the first fit carried over unchanged, as before the refit). Score both with
``benchmarks/floor_sigma_measure.py OUT/r8s1 OUT/r8s1_old ...``.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.run.options import NarrowMode
from rigsfm.run.pipeline import RunOptions, run
from rigsfm.run.world import frame
from rigsfm.synth.dataset import render_dataset, scale_with_floor_bar
from rigsfm.synth.scene import SceneOptions

first = {}
refit = frame.WorldResult.refit


def keep_first(self, reconstruction, scale):
    first["fit"] = self.estimate.fit
    return refit(self, reconstruction, scale)


frame.WorldResult.refit = keep_first

out = Path(sys.argv[1])
for arg in sys.argv[2:]:
    seed, _, mode = arg.partition(":")
    base = out / f"r8s{seed}"
    if not (base / "scene").exists():
        dataset = render_dataset(base / "scene", SceneOptions(num_rigs=8, arc_deg=360.0, image_scale=0.5, seed=int(seed),
                                                              persons_per_m2=4.0, narrow_extra_pitch_deg=-4.0))
        scale_with_floor_bar(dataset, base / "scale.yaml")
    root = out / f"r8s{seed}{'_off' if mode == 'off' else ''}"
    for folder in (root, root.parent / f"{root.name}_old"):
        folder.mkdir(parents=True, exist_ok=True)
        if not (folder / "scene").exists():
            (folder / "scene").symlink_to((base / "scene").resolve())
    first.clear()
    run(base / "scene" / "images", base / "scene" / "rigs.yaml", root / "run", base / "scale.yaml",
        RunOptions(narrow=NarrowMode.OFF if mode == "off" else NarrowMode.AUTO, overwrite=True))
    summary = json.loads((root / "run" / "summary.json").read_text())
    floor = summary["world"]["floor"]
    model = pycolmap.Reconstruction(str(root / "run" / "sparse"))
    old = first.get("fit")
    if old:  # delivered = new floor_from_model * model; before the refit: the first fit's
        new = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array(floor["floor_from_mapping"]["rotation"])),
                               np.array(floor["floor_from_mapping"]["translation"]))
        stale = old.floor_from_model * new.inverse()
        model.transform(pycolmap.Sim3d(1.0, stale.rotation, stale.translation))
    (root.parent / f"{root.name}_old" / "run" / "sparse").mkdir(parents=True, exist_ok=True)
    model.write(str(root.parent / f"{root.name}_old" / "run" / "sparse"))
    floor["normal_sigma_deg"] = old.scatter_normal_sigma_deg if old else floor["scatter_normal_sigma_deg"]
    floor["camera_height_sigma"] = old.scatter_height_sigma if old else floor["scatter_camera_height_sigma"]
    floor.pop("narrow_camera_heights", None)
    (root.parent / f"{root.name}_old" / "run" / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"{root.name}: refitted {floor.get('refitted_after_narrow_adjustment')}", flush=True)
