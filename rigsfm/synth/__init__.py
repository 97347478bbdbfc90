"""A rendered synthetic arena with exact ground truth: hybrid wide + narrow rigs round a homogeneous centre.

``render_dataset(out_dir, SceneOptions(...))`` writes images, rigs.yaml, scale.yaml and a
ground-truth ``pycolmap.Reconstruction``; ``python -m rigsfm.synth OUT`` does the same from a shell.
"""

from rigsfm.synth.cameras import RigTruth, make_rigs
from rigsfm.synth.dataset import SyntheticDataset, render_dataset
from rigsfm.synth.persons import read_person_truth
from rigsfm.synth.render import pixel_rays, render_clean, render_image
from rigsfm.synth.scene import Arena, Bar, SceneOptions, build_arena

__all__ = [
    "Arena",
    "Bar",
    "RigTruth",
    "SceneOptions",
    "SyntheticDataset",
    "build_arena",
    "make_rigs",
    "pixel_rays",
    "read_person_truth",
    "render_clean",
    "render_dataset",
    "render_image",
]
