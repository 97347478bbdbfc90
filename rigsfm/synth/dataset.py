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
  persons/           with persons_per_m2 > 0: every head's truth (rigsfm.synth.persons: heads.csv, frameNNNN.json)
```

Rig ``r``'s frame ``k`` is taken at time ``(k + offset_r) * frame_period_s`` (``frame_offsets``); only the persons
move. With ``jpeg_quality`` the images are ``frameNNNN.jpg``; with ``exposure_jitter`` each image's brightness is
scaled by its own gain (scene.yaml lists them).
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
from typing import Any

import cv2
import numpy as np
import pycolmap
import yaml

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.geometry import project_world
from rigsfm.core.io import parse_yaml, sha256_file, write_bytes_atomic, write_json_atomic
from rigsfm.core.names import SENSORS, ImageName, Sensor
from rigsfm.core.rig import RigCalibration, add_posed_rig, rigs_to_yaml
from rigsfm.synth.cameras import RigTruth, calibration_error_sigmas, make_rigs, user_calibration
from rigsfm.synth.persons import (
    HEAD,
    HEAD_RADIUS,
    VISIBILITY_SAMPLES,
    Crowd,
    HeadsInImage,
    build_crowd,
    head_samples,
    heads_csv,
)
from rigsfm.synth.render import render_clean, to_uint8, visible
from rigsfm.synth.scene import PERSON, Arena, Bar, SceneOptions, build_arena, trace

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


def image_name(rig: str, sensor: str, frame: int, suffix: str = ".png") -> str:
    """Image name relative to ``images/``, as in the ground truth: ``rig01/wide/frame0000.png``."""
    return str(ImageName(rig, Sensor(sensor), f"frame{frame:04d}{suffix}"))


def image_suffix(options: SceneOptions) -> str:
    return ".jpg" if options.jpeg_quality > 0 else ".png"


def choose_bar(arena: Arena, first: RigTruth, second: RigTruth, crowd: Crowd | None = None) -> Bar | None:
    """A bar on the textured ground, fully visible in both wide images (frame 0, in front of the ``crowd`` of that
    instant), as long in pixels as possible; None when the two views share no room for it (rigs nearly facing each
    other with narrow lenses)."""
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
    obj: Any  # a pillar or a box
    for obj in (*arena.pillars, *arena.boxes):
        reach = getattr(obj, "radius", None) or float(np.hypot(*obj.half_size[:2]))
        for p in (a, mid, b):
            ok &= np.hypot(p[:, 0] - obj.x, p[:, 1] - obj.y) > reach + ring + 0.5
    score = np.full(len(mid), np.inf)
    for rig in (first, second):
        cam, pose = rig.wide, rig.wide_from_world
        margin = 0.06 * cam.width
        seen = arena if crowd is None else arena.with_persons(crowd.at(arena.options.frame_offset(rig.name)))
        for p in (a, mid, b, a - tangent * ring, b + tangent * ring):
            ok &= visible(seen, cam, pose, p, margin)
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


def ground_truth_reconstruction(rigs: list[RigTruth], frames_per_rig: int, suffix: str = ".png",
                                ) -> pycolmap.Reconstruction:
    """Exact cameras, one pycolmap.Rig per rig (wide = reference sensor), frames and images."""
    rec = pycolmap.Reconstruction()
    for index, truth in enumerate(rigs):
        frames = [{sensor: image_name(truth.name, sensor, frame, suffix) for sensor in SENSORS}
                  for frame in range(frames_per_rig)]
        # Sensor is a str
        add_posed_rig(rec, index + 1, truth.calibration(), truth.wide_from_world, frames)  # type: ignore[arg-type]
    return rec


def _scale_yaml(rigs: list[RigTruth], bar: Bar | None, first: RigTruth, second: RigTruth, suffix: str = ".png",
                ) -> str:
    far = max(rigs[1:], key=lambda rig: float(np.linalg.norm(rig.centre() - rigs[0].centre())))
    observations = []
    for rig in (first, second) if bar is not None else ():
        # a bar is placed with the scale
        a, b = project_world(rig.wide, rig.wide_from_world, np.stack([bar.a, bar.b]), margin_px=None)[0]  # type: ignore[union-attr]
        observations.append(
            {"image": image_name(rig.name, "wide", 0, suffix), "a": [float(v) for v in a],
             "b": [float(v) for v in b]}
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


def scale_with_floor_bar(dataset: SyntheticDataset, path: Path) -> Path:
    """The dataset's scale.yaml where it holds a known length; else (its crowd left no room for the bar in both
    first rigs' wide images: a camera distance only, so a run finds no floor) one written to ``path`` with the
    bar's exact end points in those two images, where the crowd may hide it, as a surveyor's marks would give."""
    if "known_length" in Path(dataset.scale).read_text(encoding="utf-8") or not dataset.options.persons_per_m2:
        return dataset.scale
    rigs = make_rigs(dataset.options)
    bar = choose_bar(build_arena(dataset.options), rigs[0], rigs[1])
    if bar is None:
        return dataset.scale
    Path(path).write_text(_scale_yaml(rigs, bar, rigs[0], rigs[1], image_suffix(dataset.options)), encoding="utf-8")
    return Path(path)


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
        self.root = root
        self.files: dict = {}

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
            raise WorkspaceError(f"'{out_dir}' holds files rigsfm did not write there, or changed since "
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


def _encode_image(path: Path, image: np.ndarray, options: SceneOptions) -> bytes:
    params = [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality] if options.jpeg_quality > 0 else []
    ok, data = cv2.imencode(path.suffix, image, params)
    if not ok:
        raise OSError(f"could not encode {path}")
    return data.tobytes()


def heads_in_image(arena: Arena, camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d) -> HeadsInImage:
    """The heads of ``arena.persons`` whose centre projects inside the image, with their visibility (the share of
    rays to points over each head's silhouette that first meet that head; the first point is the centre)."""
    persons = arena.persons
    centres = persons.head_centres()  # type: ignore[union-attr]  # persons asked for
    xy, inside = project_world(camera, cam_from_world, centres, margin_px=0.0)
    ids = np.flatnonzero(inside)
    if not len(ids):
        return HeadsInImage(ids, np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0))
    eye = np.asarray(cam_from_world.inverse().translation, dtype=np.float64)
    points = head_samples(centres[ids], eye).reshape(-1, 3)
    rays = points - eye
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    hits = trace(arena, eye, rays)
    own = (hits.kind == PERSON) & (hits.object_index == np.repeat(ids, VISIBILITY_SAMPLES))
    own &= hits.u == HEAD
    own = own.reshape(len(ids), -1)
    return HeadsInImage(ids, xy[ids], own[:, 0], own.mean(axis=1))


def _write_person_truth(written: _Written, folder: Path, options: SceneOptions, rigs: list[RigTruth], crowd: Crowd,
                        rows: list[tuple[str, HeadsInImage]]) -> None:
    for frame in range(options.frames_per_rig):
        instants: dict[float, int] = {}
        entries = {}
        for rig in rigs:
            time_frames = frame + options.frame_offset(rig.name)
            instant = instants.setdefault(time_frames, len(instants))
            entries[rig.name] = {"offset_frames": options.frame_offset(rig.name),
                                 "time_s": time_frames * options.frame_period_s, "instant": instant}
        data = {
            "frame": frame,
            "period_s": options.frame_period_s,
            "head_radius_m": HEAD_RADIUS,
            "rigs": entries,
            "instants": [{"time_s": t * options.frame_period_s,
                          "heads": np.round(crowd.at(t).head_centres(), 6).tolist()} for t in instants],
        }
        written.write(folder / f"frame{frame:04d}.json", json.dumps(data, separators=(",", ":")).encode("utf-8"))
    written.write(folder / "heads.csv", heads_csv(rows).encode("utf-8"))


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
    times = sorted({frame + options.frame_offset(rig.name) for rig in rigs
                    for frame in range(options.frames_per_rig)})
    crowd = build_crowd(options, times)
    bar = choose_bar(arena, first, second, crowd)
    arena = arena.with_bar(bar)

    suffix = image_suffix(options)
    names, gains, person_rows = [], {}, []
    written = _Written(out_dir)
    try:
        for index, truth in enumerate(rigs):
            for s, sensor in enumerate(SENSORS):
                camera = truth.wide if sensor == "wide" else truth.narrow
                pose = truth.wide_from_world if sensor == "wide" else truth.narrow_from_world
                clean, instant = None, None
                for frame in range(options.frames_per_rig):
                    time_frames = frame + options.frame_offset(truth.name)
                    if clean is None or (crowd is not None and time_frames != instant):
                        scene = arena if crowd is None else arena.with_persons(crowd.at(time_frames))
                        clean, instant = render_clean(scene, camera, pose), time_frames
                        if crowd is not None:
                            heads = heads_in_image(scene, camera, pose)
                    rng = np.random.default_rng([options.seed, 41, index, s, frame])
                    name = image_name(truth.name, sensor, frame, suffix)
                    image = clean
                    if options.exposure_jitter > 0:
                        gain = np.random.default_rng([options.seed, 43, index, s, frame]).uniform(
                            1 - options.exposure_jitter, 1 + options.exposure_jitter)
                        gains[name] = float(gain)
                        image = clean * gain
                    written.write(out_dir / "images" / name,
                                  _encode_image(out_dir / "images" / name, to_uint8(image, rng, options.noise_sigma),
                                                options))
                    names.append(name)
                    if crowd is not None:
                        person_rows.append((name, heads))
            written.save()
            logger.info("rendered %s (%d/%d)", truth.name, index + 1, len(rigs))
        if crowd is not None:
            _write_person_truth(written, out_dir / "persons", options, rigs, crowd, person_rows)

        rigs_text = (rigs_yaml_with_sigmas(user_calibration(rigs, options)) if options.calibration_noise
                     else rigs_to_yaml(user_calibration(rigs, options)))
        written.write(out_dir / "rigs.yaml", rigs_text.encode("utf-8"))
        written.write(out_dir / "rigs_exact.yaml", rigs_to_yaml([rig.calibration() for rig in rigs]).encode("utf-8"))
        written.write(out_dir / "scale.yaml", _scale_yaml(rigs, bar, first, second, suffix).encode("utf-8"))
        scene_yaml: dict[str, object] = {
            "options": dataclasses.asdict(options),
            "bar": {"a": [float(v) for v in bar.a], "b": [float(v) for v in bar.b]} if bar is not None else None,
        }
        if gains:
            scene_yaml["exposure_gain"] = gains
        written.write(out_dir / "scene.yaml",
                      yaml.safe_dump(scene_yaml, sort_keys=False, default_flow_style=None).encode("utf-8"))
        gt_dir = out_dir / "ground_truth"
        gt_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="rigsfm-ground-truth-") as tmp:  # outside OUT: no leftover there
            ground_truth_reconstruction(rigs, options.frames_per_rig, suffix).write(tmp)
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
