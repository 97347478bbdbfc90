"""Epipolar geometry an analyst can trust: band coverage, accuracy against the fixed-calibration oracle,
the measurement-constrained 4-rig circle, and the cost of the adjustment + covariance + band.

    python benchmarks/trust.py prepare [NAME ...]   # render + map each scene once (cached under --work)
    python benchmarks/trust.py measure [NAME ...]   # both adjustments, bands, scores: WORK/results/<name>.json
    python benchmarks/trust.py report [--measured benchmarks/measured_trust.json]   # tables: stdout, WORK/trust.md
    python benchmarks/trust.py all                  # the three in turn
    options: --work DIR (default benchmarks/results/trust), --force (redo cached steps)

Scenes (``scenes()``): rendered arenas (``rigsfm.synth``) at image scale 0.5 with the synthetic calibration error of a
good board calibration in rigs.yaml (focal +-0.05..0.15 %, principal point +-0.2..0.8 px, E^sl rotated 0.05..0.1 deg,
+-1 mm; no sigmas in rigs.yaml, so rigsfm assumes its documented good-board defaults): 2 rigs 60 deg apart (the
paper's setting) with featureless and textured centres, 4-rig circles with two rangefinder distances on adjacent
sides, 4 rigs 45 deg apart with textured narrow views, 8- and 16-rig circles; several seeds each. Each scene is
mapped once (database, features, matching, mapping: the stages before ``adjust``); ``measure`` runs on the saved
mapping model:

- ``fixed``: ``--fixed-calibration`` (the calibration held, as rigsfm did before it refined it) with its consider-covariance band;
- ``refine``: the default adjustment (calibration priors, measurements inside) with its posterior band;
- the fixed-calibration oracle (``rigsfm.synth.truth.oracle``): the fixed stage started from the true poses.

Coverage: 400 true floor points (z = 0) on random pixels of the true narrow camera i, seen by the true narrow j;
their true correspondences' distances from the estimated epipolar lines (``uncertainty.correspondence_check``)
against the pair's band. Run niced; every step logs to WORK/trust.log.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
import yaml  # noqa: E402

from rigsfm.core.io import write_json_atomic  # noqa: E402
from rigsfm.synth.scene import SceneOptions  # noqa: E402

if TYPE_CHECKING:
    from rigsfm.run.adjustment.priors import CalibrationPriors
    from rigsfm.run.pipeline import Inputs

logger = logging.getLogger("benchmarks.trust")
DEFAULT_WORK = REPO / "benchmarks" / "results" / "trust"


@dataclass(frozen=True)
class Scene:
    name: str
    group: str
    options: SceneOptions
    narrow_features: bool = False
    two_sides: bool = False  # scale.yaml: rangefinder distances rig01-rig02 and rig02-rig03 (instead of the default)


def scenes() -> dict[str, Scene]:
    out = []
    for seed in range(6):
        out.append(Scene(f"r2_s{seed}", "2 rigs 60°, featureless", SceneOptions(num_rigs=2, arc_deg=60, image_scale=0.5,
                                                                                 seed=seed)))
    for seed in range(3):
        out.append(Scene(f"r2t_s{seed}", "2 rigs 60°, textured, narrow features",
                         SceneOptions(num_rigs=2, arc_deg=60, image_scale=0.5, seed=seed, textured_centre=True), True))
    for seed in range(3):
        out.append(Scene(f"r4_s{seed}", "4-rig circle, 2 rangefinder sides",
                         SceneOptions(num_rigs=4, image_scale=0.5, seed=seed), two_sides=True))
    for seed in range(3):
        out.append(Scene(f"r4t_s{seed}", "4 rigs 45°, textured, narrow features",
                         SceneOptions(num_rigs=4, arc_deg=45, image_scale=0.5, seed=seed, textured_centre=True), True))
    for seed in range(4):
        out.append(Scene(f"r8_s{seed}", "8-rig circle, featureless", SceneOptions(num_rigs=8, image_scale=0.5, seed=seed)))
    for seed in range(2):
        out.append(Scene(f"r8t_s{seed}", "8-rig circle, textured, narrow features",
                         SceneOptions(num_rigs=8, image_scale=0.5, seed=seed, textured_centre=True), True))
    for seed in range(2):
        out.append(Scene(f"r16_s{seed}", "16-rig circle, featureless", SceneOptions(num_rigs=16, image_scale=0.5,
                                                                                     seed=seed)))
    return {s.name: s for s in out}


# ------------------------------------------------------------------------------------------------------------
# prepare: render and map once


def two_sides_scale(scene_dir: Path) -> Path:
    """scale_two_sides.yaml: true distances rig01-rig02 and rig02-rig03 (two diagonals of a 4-rig circle do not fix
    it: with the link directions known, a parallelogram's aspect ratio leaves both diagonals equal)."""
    truth = pycolmap.Reconstruction(str(scene_dir / "ground_truth"))
    entries = []
    for a, b in (("rig01", "rig02"), ("rig02", "rig03")):
        ca = truth.find_image_with_name(f"{a}/wide/frame0000.png").projection_center()
        cb = truth.find_image_with_name(f"{b}/wide/frame0000.png").projection_center()
        entries.append({"a": f"{a}/wide", "b": f"{b}/wide", "meters": float(np.linalg.norm(ca - cb))})
    path = scene_dir / "scale_two_sides.yaml"
    path.write_text(yaml.safe_dump({"camera_distance": entries}, sort_keys=False))
    return path


def ensure_sigmas(scene_dir: Path) -> None:
    """rigs.yaml with the synthetic calibration error's sigmas (scenes rendered before render_dataset wrote them)."""
    from rigsfm.calibrate.uncertainty import load_sigmas
    from rigsfm.core.io import write_text_atomic
    from rigsfm.core.rig import load_rigs
    from rigsfm.synth.dataset import rigs_yaml_with_sigmas

    path = scene_dir / "rigs.yaml"
    if any(s.wide is None for s in load_sigmas(path).values()):
        write_text_atomic(path, rigs_yaml_with_sigmas(load_rigs(path)))


def prepare(scene: Scene, work: Path, force: bool = False) -> None:
    from rigsfm.core.workspace import Workspace, colmap_log_to
    from rigsfm.run.inputs.database import create_database
    from rigsfm.run.mapping.mapper import run_mapping
    from rigsfm.run.matching.extract import extract_features
    from rigsfm.run.matching.match import match_features
    from rigsfm.run.options import MappingOptions, MatchingOptions
    from rigsfm.run.pipeline import load_inputs
    from rigsfm.synth.dataset import render_dataset

    root = work / "scenes" / scene.name
    done = root / "prepared.json"
    if done.exists() and not force:
        return
    start = time.perf_counter()
    dataset = render_dataset(root / "scene", scene.options, overwrite=True)
    rendered = time.perf_counter() - start
    if scene.two_sides:
        two_sides_scale(root / "scene")
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)
    workspace = Workspace(root / "run")
    workspace.root.mkdir(parents=True, exist_ok=True)
    matching = MatchingOptions(narrow_features=scene.narrow_features)
    record = {"render_s": rendered}
    try:
        with colmap_log_to(workspace.colmap_log):
            create_database(workspace.database, inputs.rigs, inputs.images)
            t = time.perf_counter()
            extract_features(workspace.database, inputs.image_dir, inputs.images, matching)
            match_features(workspace.database, inputs.images, matching, workspace.pairs)
            record["features_s"] = time.perf_counter() - t
            t = time.perf_counter()
            num_wide = sum(e.sensor == "wide" for e in inputs.images)
            mapping = run_mapping(workspace, inputs.image_dir, MappingOptions(), num_wide=num_wide)
            record["mapping_s"] = time.perf_counter() - t
            record["registered_frames"] = mapping.reconstruction.num_reg_frames()
    except Exception as error:  # noqa: BLE001 - a scene that fails is recorded, not fatal
        record["error"] = repr(error)
    write_json_atomic(done, record)
    logger.info("prepared %s in %.0f s: %s", scene.name, time.perf_counter() - start, record)


# ------------------------------------------------------------------------------------------------------------
# measure


def true_floor_points(truth: pycolmap.Reconstruction, name: str, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """World points on the floor (z = 0) on random pixels of the true camera ``name``."""
    image = truth.find_image_with_name(name)
    camera = truth.cameras[image.camera_id]
    pixels = rng.uniform([0, 0], [camera.width, camera.height], (n, 2))
    rays = np.column_stack([np.asarray(camera.cam_from_img(pixels)), np.ones(n)])
    world_from_cam = image.cam_from_world().inverse()
    origin = np.asarray(world_from_cam.translation)
    directions = rays @ world_from_cam.rotation.matrix().T
    s = -origin[2] / directions[:, 2]
    keep = s > 0
    return origin + s[keep, None] * directions[keep]


def pair_errors(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> dict:
    """Per narrow pair "i|j": relative-rotation error (deg) and centre-distance error (%)."""
    from rigsfm.core.conventions import rotation_angle_deg
    from rigsfm.run.deliver import narrow_images

    est = {im.name: im for im in narrow_images(estimate)}
    names = sorted(est)
    out = {}
    for k, a in enumerate(names):
        for b in names[k + 1:]:
            e = est[b].cam_from_world() * est[a].cam_from_world().inverse()
            g = truth.find_image_with_name(b).cam_from_world() * truth.find_image_with_name(a).cam_from_world().inverse()
            distance = np.linalg.norm(g.translation)
            out[f"{a}|{b}"] = {"rotation_deg": rotation_angle_deg(e.rotation.matrix(), g.rotation.matrix()),
                               "distance_percent": float(100 * (np.linalg.norm(e.translation) - distance) / distance)}
    return out


def score_bands(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, bands: dict) -> list[dict]:
    from rigsfm.core.geometry import correspondence_check

    rows = []
    for (name_i, name_j), band in sorted(bands.items()):
        rng = np.random.default_rng(zlib.crc32(f"{name_i}|{name_j}".encode()))  # not hash(): salted per process
        distances = correspondence_check(estimate, truth, name_i, name_j, true_floor_points(truth, name_i, rng))
        if len(distances) < 10:
            continue
        rows.append({"pair": [name_i, name_j], "band_px": band.band_px, "points": band.points,
                     "num_true_points": int(len(distances)), "coverage": float(np.mean(distances <= band.band_px)),
                     "true_median_px": float(np.median(distances)), "true_p95_px": float(np.quantile(distances, 0.95)),
                     "predicted_below_85": band.predicted_below_85,
                     "predicted_coverage_mean": float(np.mean(band.predicted_coverage))})
    return rows


@dataclass
class Prepared:
    """A prepared scene read back for measuring: its inputs (rigs.yaml with sigmas, the scale file), the
    priors, the mapping model and the ground truth."""

    inputs: Inputs
    priors: CalibrationPriors
    mapped: pycolmap.Reconstruction
    truth: pycolmap.Reconstruction
    scale_file: str


def load_prepared(scene: Scene, work: Path) -> Prepared | str:
    """The scene ``prepare`` made under ``work``, or the error that stopped it."""
    from rigsfm.run.adjustment.priors import calibration_priors
    from rigsfm.run.pipeline import load_inputs

    root = work / "scenes" / scene.name
    prepared = json.loads((root / "prepared.json").read_text())
    if "error" in prepared:
        return prepared["error"]
    ensure_sigmas(root / "scene")
    scale_path = root / "scene" / ("scale_two_sides.yaml" if scene.two_sides else "scale.yaml")
    inputs = load_inputs(root / "scene" / "images", root / "scene" / "rigs.yaml", scale_path)
    return Prepared(inputs, calibration_priors(inputs.rigs, root / "scene" / "rigs.yaml"),
                    pycolmap.Reconstruction(str(root / "run" / "mapping")),
                    pycolmap.Reconstruction(str(root / "scene" / "ground_truth")), scale_path.name)


def measure(scene: Scene, work: Path, force: bool = False) -> dict | None:
    from rigsfm.run.adjustment.adjust import adjust
    from rigsfm.run.adjustment.uncertainty import estimate_uncertainty
    from rigsfm.run.options import AdjustOptions, Calibration
    from rigsfm.run.world.analysis_floor import find_floor
    from rigsfm.synth.truth import compare_to_ground_truth, oracle

    out_path = work / "results" / f"{scene.name}.json"
    if out_path.exists() and not force:
        return json.loads(out_path.read_text())
    prepared = load_prepared(scene, work)
    if isinstance(prepared, str):
        result = {"scene": scene.name, "group": scene.group, "error": prepared}
        write_json_atomic(out_path, result)
        return result
    inputs, priors, mapped, truth = prepared.inputs, prepared.priors, prepared.mapped, prepared.truth
    result = {"scene": scene.name, "group": scene.group, "frames": mapped.num_reg_frames(),
              "points": mapped.num_points3D(), "scale_file": prepared.scale_file, "timings_s": {}, "variants": {}}
    estimates = {}
    for variant, calibration in (("fixed", Calibration.FIXED), ("refine", Calibration.REFINE)):
        t = time.perf_counter()
        adjusted = adjust(mapped, inputs.rigs, inputs.scale, AdjustOptions(calibration=calibration), priors)
        adjust_s = time.perf_counter() - t
        t = time.perf_counter()
        plane, source = find_floor(adjusted.reconstruction, adjusted.scale_spec)
        uncertainty = estimate_uncertainty(adjusted, floor=plane, floor_source=source)
        rec = adjusted.reconstruction
        estimates[variant] = rec
        result["variants"][variant] = {
            "adjust_s": adjust_s, "covariance_s": uncertainty.seconds.get("covariance"),
            "bands_s": uncertainty.seconds.get("bands"), "uncertainty_s": time.perf_counter() - t,
            "rounds": adjusted.rounds, "pixel_sigma": adjusted.pixel_sigma, "floor": uncertainty.floor,
            "scale_relative_sigma": adjusted.scale_relative_sigma,
            "measurements": adjusted.scale.residuals() if adjusted.scale else [],
            "accuracy": compare_to_ground_truth(rec, truth, "narrow"),
            "pair_errors": pair_errors(rec, truth),
            "narrow_uncertainty": {k: vars(v) for k, v in uncertainty.narrow.items()},
            "bands": score_bands(rec, truth, uncertainty.bands),
            "narrow_observations": int(sum(im.num_points3D for im in rec.images.values()
                                           if im.has_pose and "/narrow/" in im.name)),
        }
    t = time.perf_counter()
    limit = oracle(estimates["fixed"], truth, inputs.rigs, inputs.scale)
    result["timings_s"]["oracle"] = time.perf_counter() - t
    result["variants"]["oracle"] = {"accuracy": compare_to_ground_truth(limit, truth, "narrow"),
                                    "pair_errors": pair_errors(limit, truth)}
    write_json_atomic(out_path, result)
    return result


# ------------------------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("prepare", "measure", "report", "all"))
    parser.add_argument("names", nargs="*")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--measured", type=Path, help="report: the tables of this saved copy of the results "
                                                       "(benchmarks/measured_trust.json) instead of WORK/results")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s",
                        handlers=[logging.FileHandler(args.work / "trust.log"), logging.StreamHandler()])
    for noisy in ("rigsfm.run.mapping.mapper", "rigsfm.run.matching.extract", "rigsfm.run.adjustment.scale", "rigsfm.run.inputs.database"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    chosen = [scenes()[n] for n in args.names] if args.names else list(scenes().values())
    if args.step in ("prepare", "all"):
        for scene in chosen:
            try:
                prepare(scene, args.work, args.force)
            except Exception:  # noqa: BLE001
                logger.error("prepare %s failed:\n%s", scene.name, traceback.format_exc())
    if args.step in ("measure", "all"):
        for scene in chosen:
            t = time.perf_counter()
            try:
                measure(scene, args.work, args.force)
                logger.info("measured %s in %.0f s", scene.name, time.perf_counter() - t)
            except Exception:  # noqa: BLE001
                logger.error("measure %s failed:\n%s", scene.name, traceback.format_exc())
    if args.step in ("report", "all"):
        from benchmarks.trust_report import write_report

        print(write_report(args.work, [s.name for s in chosen], args.measured))


if __name__ == "__main__":
    main()
