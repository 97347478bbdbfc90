"""Write a whole synthetic dataset: images, rigs.yaml (+ exact), scale.yaml and the ground truth.

```
OUT/
  images/rig01/wide/frame0000.png, images/rig01/narrow/frame0000.png, ...
  rigs.yaml          the calibration a user would have (perturbed if calibration_noise, with that error's sigmas)
  rigs_exact.yaml    the exact calibration used for rendering
  scale.yaml         camera_distance (rig01 to the farthest rig) + known_length (a 2 m bar)
  scene.yaml         the SceneOptions and the bar's world end points, for reference
  ground_truth/      pycolmap.Reconstruction (binary): cameras, rigs, frames, images; no points
  .rigsfm-dataset.json  every file above and its SHA-256: all that overwrite=True may remove
```
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import re
import stat
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import yaml

from rigsfm.core.geometry import project_world
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.names import SENSORS, ImageName, Sensor
from rigsfm.core.io import parse_yaml, sha256_file, write_bytes_atomic, write_json_atomic
from rigsfm.core.rig import RigCalibration, add_posed_rig, rigs_to_yaml
from rigsfm.synth.cameras import RigTruth, calibration_error_sigmas, make_rigs, user_calibration
from rigsfm.synth.render import render_clean, to_uint8, visible
from rigsfm.synth.scene import Arena, Bar, SceneOptions, build_arena

logger = logging.getLogger(__name__)



@dataclass(frozen=True)
class SyntheticDataset:
    """Paths of a rendered dataset (see the module docstring for the layout)."""

    root: Path
    images: Path
    rigs: Path
    rigs_exact: Path
    scale: Path
    ground_truth: Path
    options: SceneOptions
    image_names: tuple[str, ...]

    def load_ground_truth(self) -> pycolmap.Reconstruction:
        from rigsfm.core.workspace import read_model

        return read_model(self.ground_truth, f"render the scene again (overwrite=True) into {self.root}")


def image_name(rig: str, sensor: str, frame: int) -> str:
    """Image name relative to ``images/``, as in the ground truth: ``rig01/wide/frame0000.png``."""
    return str(ImageName(rig, Sensor(sensor), f"frame{frame:04d}.png"))


def choose_bar(arena: Arena, first: RigTruth, second: RigTruth) -> Bar | None:
    """A bar on the textured ground, fully visible in both wide images, as long in pixels as possible;
    None when the two views share no room for it (rigs nearly facing each other with narrow lenses)."""
    opt = arena.options
    radii = np.linspace(opt.centre_radius + 1.5, opt.wall_radius - 1.5, 10)
    angles = np.radians(np.arange(0.0, 360.0, 3.0))
    headings = np.radians([0.0, 45.0, 90.0, 135.0])
    r, phi, heading = (g.ravel() for g in np.meshgrid(radii, angles, headings, indexing="ij"))
    mid = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros_like(r)], axis=1)
    tangent = np.stack([-np.sin(phi + heading), np.cos(phi + heading), np.zeros_like(r)], axis=1)
    a, b = mid - tangent * opt.bar_length / 2, mid + tangent * opt.bar_length / 2
    ring = Bar(np.zeros(3), np.zeros(3)).ring_radius
    ok = np.ones(len(mid), dtype=bool)
    for end in (a, b):
        ok &= np.hypot(end[:, 0], end[:, 1]) > opt.centre_radius + 1.2 + ring
        ok &= np.hypot(end[:, 0], end[:, 1]) < opt.wall_radius - 1.0
    for obj in (*arena.pillars, *arena.boxes):
        reach = getattr(obj, "radius", None) or float(np.hypot(*obj.half_size[:2]))
        for p in (a, mid, b):
            ok &= np.hypot(p[:, 0] - obj.x, p[:, 1] - obj.y) > reach + ring + 0.5
    score = np.full(len(mid), np.inf)
    for rig in (first, second):
        cam, pose = rig.wide, rig.wide_from_world
        margin = 0.06 * cam.width
        for p in (a, mid, b, a - tangent * ring, b + tangent * ring):
            ok &= visible(arena, cam, pose, p, margin)
        ends = [project_world(cam, pose, end, margin_px=None)[0] for end in (a, b)]
        length = np.linalg.norm(ends[0] - ends[1], axis=1)
        score = np.minimum(score, np.nan_to_num(length, nan=0.0))
    if not np.any(ok):
        logger.warning("no room for the known-length bar in both %s and %s: scale.yaml gives a camera "
                       "distance only", first.name, second.name)
        return None
    best = int(np.argmax(np.where(ok, score, -1.0)))
    logger.info(
        "bar at r=%.1f m, azimuth %.0f deg, %.0f px long", r[best], np.degrees(phi[best]), score[best]
    )
    return Bar(a[best], b[best])


def ground_truth_reconstruction(rigs: list[RigTruth], frames_per_rig: int) -> pycolmap.Reconstruction:
    """Exact cameras, one pycolmap.Rig per rig (wide = reference sensor), frames and images."""
    rec = pycolmap.Reconstruction()
    for index, truth in enumerate(rigs):
        frames = [{sensor: image_name(truth.name, sensor, frame) for sensor in SENSORS}
                  for frame in range(frames_per_rig)]
        add_posed_rig(rec, index + 1, truth.calibration(), truth.wide_from_world, frames)
    return rec


def _scale_yaml(rigs: list[RigTruth], bar: Bar | None, first: RigTruth, second: RigTruth) -> str:
    far = max(rigs[1:], key=lambda rig: float(np.linalg.norm(rig.centre() - rigs[0].centre())))
    observations = []
    for rig in (first, second) if bar is not None else ():
        a, b = project_world(rig.wide, rig.wide_from_world, np.stack([bar.a, bar.b]), margin_px=None)[0]
        observations.append(
            {"image": image_name(rig.name, "wide", 0), "a": [float(v) for v in a], "b": [float(v) for v in b]}
        )
    data = {
        "camera_distance": [
            {
                "a": f"{rigs[0].name}/wide",
                "b": f"{far.name}/wide",
                "meters": float(np.linalg.norm(far.centre() - rigs[0].centre())),
            }
        ],
    }
    if bar is not None:
        data["known_length"] = [{"meters": bar.length, "observations": observations}]
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


def rigs_yaml_with_sigmas(calibrations: list[RigCalibration]) -> str:
    """rigs.yaml with the sigmas of the synthetic calibration error (``cameras.calibration_error_sigmas``), as
    ``rigsfm calibrate`` writes its own: the run then weighs rigs.yaml by its real uncertainty."""
    from rigsfm.calibrate.uncertainty import RigSigmas, add_sigmas

    data = parse_yaml(rigs_to_yaml(calibrations))
    for entry, calibration in zip(data["rigs"], calibrations, strict=True):
        sigmas = calibration_error_sigmas(calibration)
        add_sigmas(entry, RigSigmas(wide=sigmas["wide"], narrow=sigmas["narrow"], rotation_deg=sigmas["rotation_deg"],
                                    translation_m=sigmas["translation_m"]))
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


MANIFEST = ".rigsfm-dataset.json"
_LEFTOVER = re.compile(r"\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp")  # what an atomic write that was killed leaves


class _Written:
    """The files a render wrote under its folder with their SHA-256, saved in its manifest as they are written, so
    that a later ``overwrite`` removes exactly those (and only while they are unchanged)."""

    def __init__(self, root: Path):
        self.root, self.files = root, {}

    def write(self, path: Path, data: bytes) -> None:
        self.files[path.relative_to(self.root).as_posix()] = hashlib.sha256(data).hexdigest()  # listed first: a
        write_bytes_atomic(path, data)  # stop between the two leaves a listed name, never an unlisted file

    def record(self, path: Path) -> None:
        self.files[path.relative_to(self.root).as_posix()] = sha256_file(path)

    def save(self) -> None:
        write_json_atomic(self.root / MANIFEST, {"written_by": "rigsfm.synth.render_dataset", "files": self.files})


def _listed(out_dir: Path) -> dict[str, str]:
    """The manifest's entries that name a file under ``out_dir`` (relative, no ``..``), with their SHA-256."""
    manifest = out_dir / MANIFEST
    if manifest.is_symlink() or not manifest.is_file():
        return {}
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, dict):
        return {}
    return {name: digest for name, digest in files.items()
            if isinstance(name, str) and isinstance(digest, str) and name and not name.startswith("/")
            and "\\" not in name and all(part not in ("", ".", "..") for part in name.split("/"))}


def _ours(out_dir: Path) -> tuple[list[Path], list[str]]:
    """(the files under ``out_dir`` a render wrote and that are unchanged since, those it did not write or that
    changed: relative names). Links are never followed and never ours."""
    listed = _listed(out_dir)
    ours, foreign = [], []
    for folder, dirs, files in os.walk(out_dir):
        here = Path(folder)
        for name in [*files, *(d for d in dirs if (here / d).is_symlink())]:
            path = here / name
            rel = path.relative_to(out_dir).as_posix()
            if rel == MANIFEST:
                continue
            leftover = _LEFTOVER.fullmatch(name)
            if leftover and (here / leftover["name"]).relative_to(out_dir).as_posix() in listed:
                ours.append(path)
            elif (rel in listed and stat.S_ISREG(os.lstat(path).st_mode) and sha256_file(path) == listed[rel]):
                ours.append(path)
            else:
                foreign.append(rel)
    return ours, sorted(foreign)


def _prepare(out_dir: Path, overwrite: bool) -> None:
    """Make ``out_dir``; with ``overwrite``, first remove the files an earlier render wrote there, refusing (with
    nothing removed) when it holds any other file or one changed since."""
    if out_dir.exists() and not out_dir.is_dir():
        raise WorkspaceError(f"{out_dir} exists and is not a folder; choose another one")
    if out_dir.exists() and any(out_dir.iterdir()):
        if not overwrite:
            raise WorkspaceError(f"{out_dir} is not empty: pass overwrite=True (--overwrite) to replace it")
        ours, foreign = _ours(out_dir)
        if foreign:
            raise WorkspaceError(f"{out_dir} holds files rigsfm did not write there, or changed since "
                                 f"({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); move them away or "
                                 "choose a new folder (nothing was removed)")
        for path in ours:
            path.unlink(missing_ok=True)
        for folder in sorted({p.parent for p in ours}, key=lambda p: len(p.parts), reverse=True):
            while folder != out_dir and folder.is_relative_to(out_dir):
                with contextlib.suppress(OSError):  # a folder that still holds something stays
                    folder.rmdir()
                folder = folder.parent
    out_dir.mkdir(parents=True, exist_ok=True)


def render_dataset(
    out_dir: Path, options: SceneOptions | None = None, *, overwrite: bool = False
) -> SyntheticDataset:
    """Render the arena seen by every rig and write the dataset described in the module docstring."""
    options = options or SceneOptions()
    out_dir = Path(out_dir)
    _prepare(out_dir, overwrite)
    start = time.perf_counter()
    arena = build_arena(options)
    rigs = make_rigs(options)
    first, second = rigs[0], rigs[1]
    bar = choose_bar(arena, first, second)
    arena = arena.with_bar(bar)

    names = []
    written = _Written(out_dir)
    try:
        for index, truth in enumerate(rigs):
            for s, sensor in enumerate(SENSORS):
                camera = truth.wide if sensor == "wide" else truth.narrow
                pose = truth.wide_from_world if sensor == "wide" else truth.narrow_from_world
                clean = render_clean(arena, camera, pose)
                for frame in range(options.frames_per_rig):
                    rng = np.random.default_rng([options.seed, 41, index, s, frame])
                    name = image_name(truth.name, sensor, frame)
                    ok, png = cv2.imencode(".png", to_uint8(clean, rng, options.noise_sigma))
                    if not ok:
                        raise OSError(f"could not encode {out_dir / 'images' / name}")
                    written.write(out_dir / "images" / name, png.tobytes())
                    names.append(name)
            written.save()
            logger.info("rendered %s (%d/%d)", truth.name, index + 1, len(rigs))

        rigs_text = (rigs_yaml_with_sigmas(user_calibration(rigs, options)) if options.calibration_noise
                     else rigs_to_yaml(user_calibration(rigs, options)))
        written.write(out_dir / "rigs.yaml", rigs_text.encode("utf-8"))
        written.write(out_dir / "rigs_exact.yaml", rigs_to_yaml([rig.calibration() for rig in rigs]).encode("utf-8"))
        written.write(out_dir / "scale.yaml", _scale_yaml(rigs, bar, first, second).encode("utf-8"))
        scene = {
            "options": dataclasses.asdict(options),
            "bar": {"a": [float(v) for v in bar.a], "b": [float(v) for v in bar.b]} if bar is not None else None,
        }
        written.write(out_dir / "scene.yaml",
                      yaml.safe_dump(scene, sort_keys=False, default_flow_style=None).encode("utf-8"))
        gt_dir = out_dir / "ground_truth"
        gt_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="rigsfm-ground-truth-") as tmp:  # outside OUT: no leftover there
            ground_truth_reconstruction(rigs, options.frames_per_rig).write(tmp)
            for path in sorted(Path(tmp).iterdir()):
                written.write(gt_dir / path.name, path.read_bytes())
    finally:
        written.save()
    logger.info("wrote %d images to %s in %.1f s", len(names), out_dir, time.perf_counter() - start)
    return SyntheticDataset(
        out_dir,
        out_dir / "images",
        out_dir / "rigs.yaml",
        out_dir / "rigs_exact.yaml",
        out_dir / "scale.yaml",
        gt_dir,
        options,
        tuple(names),
    )
