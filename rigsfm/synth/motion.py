"""Rendered recordings with known per-frame rig motion (shake, bumps), for tests and benchmarks.

The scene is the one :func:`rigsfm.synth.render_dataset` renders for the same ``SceneOptions`` (same
arena, bar, rigs and calibration), so a reference run on that dataset can track these frames. Each
rig's motion per frame is ``ref_from_new``: its wide camera's reference frame from the moved frame
(the same quantity ``rigsfm track`` reports as the change), so ``wide_from_world`` of a frame is
``ref_from_new.inverse() * wide_from_world`` of the reference.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.synth.cameras import RigTruth, make_rigs
from rigsfm.synth.dataset import choose_bar
from rigsfm.synth.render import render_image
from rigsfm.synth.scene import SceneOptions, build_arena

logger = logging.getLogger(__name__)


def small_motion(rng: np.random.Generator, rotation_deg: float, translation_mm: float) -> pycolmap.Rigid3d:
    """A motion by exactly ``rotation_deg`` about a random axis and ``translation_mm`` in a random direction."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    rotation = pycolmap.Rotation3d(axis_angle=axis / np.linalg.norm(axis) * np.radians(rotation_deg))
    return pycolmap.Rigid3d(rotation, direction / np.linalg.norm(direction) * translation_mm / 1000.0)


def shaken_motions(num_frames: int, rng: np.random.Generator, jitter_deg: tuple[float, float],
                   jitter_mm: tuple[float, float], bump_at: int | None = None, bump_deg: float = 0.0,
                   bump_mm: float = 0.0) -> list[pycolmap.Rigid3d]:
    """Per frame ``ref_from_new``: independent jitter (angle and shift uniform in the given ranges, random
    directions), composed from frame ``bump_at`` on with one fixed bump (``bump_deg``, ``bump_mm``)."""
    bump = small_motion(rng, bump_deg, bump_mm)
    motions = []
    for frame in range(num_frames):
        jitter = small_motion(rng, rng.uniform(*jitter_deg), rng.uniform(*jitter_mm))
        motions.append(bump * jitter if bump_at is not None and frame >= bump_at else jitter)
    return motions


@dataclass(frozen=True)
class Recording:
    images: Path  # NEW_IMAGES layout: <rig>/<wide|narrow>/frameNNNN.png
    rigs: tuple[RigTruth, ...]
    motions: dict[str, list[pycolmap.Rigid3d]]  # rig name -> per frame ref_from_new (wide camera)

    def frame_name(self, index: int) -> str:
        return f"frame{index:04d}.png"


def render_recording(out_dir: Path, options: SceneOptions, motions: dict[str, list[pycolmap.Rigid3d]], *,
                     narrow: bool = False, seed: int = 97) -> Recording:
    """Render every rig's moved frames (wide, and narrow if ``narrow``) under ``out_dir``."""
    out_dir = Path(out_dir)
    rigs = make_rigs(options)
    arena = build_arena(options)
    arena = arena.with_bar(choose_bar(arena, rigs[0], rigs[1]))
    for index, truth in enumerate(rigs):
        for frame, ref_from_new in enumerate(motions.get(truth.name, [])):
            wide_from_world = ref_from_new.inverse() * truth.wide_from_world
            poses = {"wide": (truth.wide, wide_from_world)}
            if narrow:
                poses["narrow"] = (truth.narrow, truth.narrow_from_wide * wide_from_world)
            for s, (sensor, (camera, pose)) in enumerate(poses.items()):
                rng = np.random.default_rng([options.seed, seed, index, s, frame])
                path = out_dir / truth.name / sensor / f"frame{frame:04d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                if not cv2.imwrite(str(path), render_image(arena, camera, pose, rng)):
                    raise OSError(f"could not write {path}")
        logger.info("rendered %d frames of %s", len(motions.get(truth.name, [])), truth.name)
    return Recording(out_dir, tuple(rigs), motions)
