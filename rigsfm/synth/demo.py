"""``rigsfm demo``: render the built-in arena, run the pipeline on it, and score it against the truth.

The score compares the run with the ground truth and with the oracle: the fixed-calibration adjustment
started from the true poses with the same observations, calibration file and measurements. It is a
reference, not a limit: the run refines the calibration file's errors, the oracle keeps them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.io import write_json_atomic
from rigsfm.run.pipeline import Progress, RunOptions, RunResult, load_inputs, run
from rigsfm.synth.dataset import SyntheticDataset, render_dataset
from rigsfm.synth.scene import SceneOptions
from rigsfm.synth.truth import centre_errors_mm, compare_to_ground_truth, oracle

logger = logging.getLogger(__name__)


@dataclass
class DemoResult:
    dataset: SyntheticDataset
    run: RunResult
    accuracy: dict = field(default_factory=dict)


def score(result: RunResult, dataset: SyntheticDataset) -> dict:
    """Accuracy of a run on a rendered dataset, next to the (fixed-calibration) oracle's."""
    truth = dataset.load_ground_truth()
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)
    reference = oracle(result.reconstruction, truth, inputs.rigs, inputs.scale)
    return {
        "narrow": compare_to_ground_truth(result.reconstruction, truth, "narrow"),
        "wide": compare_to_ground_truth(result.reconstruction, truth, "wide"),
        "narrow_centre_error_mm": centre_errors_mm(result.reconstruction, truth),
        "oracle_narrow": compare_to_ground_truth(reference, truth, "narrow"),
        "oracle_narrow_centre_error_mm": centre_errors_mm(reference, truth),
    }


# Below this image scale the default circle's wide images register badly or not at all (the images hold too few
# features); from it the result is at the oracle's level.
MIN_IMAGE_SCALE = 0.1


def check_image_scale(image_scale: float) -> None:
    """Refuse a demo image scale below :data:`MIN_IMAGE_SCALE` (or no number), saying the limit."""
    if not image_scale >= MIN_IMAGE_SCALE:
        raise InputError(f"--image-scale {image_scale:g} is below {MIN_IMAGE_SCALE:g}, the smallest at which the "
                         f"demo's rigs register ({round(1624 * MIN_IMAGE_SCALE)}x{round(1234 * MIN_IMAGE_SCALE)} "
                         f"images); give {MIN_IMAGE_SCALE:g} or more")


# How far apart neighbouring rigs of the demo's scene register (its wide images share too little beyond): up to 90
# degrees every rig, at 120 not all, beyond 150 none (benchmarks/README.md, *The demo's arrangements*).
REGISTERS_DEG = 90.0
NEVER_REGISTERS_DEG = 150.0


def neighbour_spacing_deg(num_rigs: int, arc_deg: float) -> float:
    """Degrees between neighbouring rigs on the demo's circle (evenly round it, or spread over the arc)."""
    return 360.0 / num_rigs if arc_deg >= 360.0 else arc_deg / max(num_rigs - 1, 1)


def check_arrangement(num_rigs: int, arc_deg: float) -> str | None:
    """Refuse rigs too far apart for the demo's scene to register any; a warning where not every rig may register
    (None where all do)."""
    spacing = neighbour_spacing_deg(num_rigs, arc_deg)
    if spacing <= REGISTERS_DEG:
        return None
    fix = (f"give --num-rigs {math.ceil(360.0 / REGISTERS_DEG)} or more on the full circle, or --arc-deg "
           f"{REGISTERS_DEG * (num_rigs - 1):g} or less" if arc_deg >= 360.0 else
           f"give --num-rigs {math.ceil(arc_deg / REGISTERS_DEG) + 1} or more, or --arc-deg "
           f"{REGISTERS_DEG * (num_rigs - 1):g} or less")
    where = f"{num_rigs} rigs {'round the full circle' if arc_deg >= 360.0 else f'over {arc_deg:g} deg'}"
    if spacing > NEVER_REGISTERS_DEG:
        raise InputError(f"{where} stand {spacing:.0f} deg apart, where the demo's wide images share too little to "
                         f"register (up to {REGISTERS_DEG:g} deg apart they do): {fix}")
    return (f"DEMO RIGS FAR APART: {where} stand {spacing:.0f} deg apart; the demo's scene registers every rig up "
            f"to {REGISTERS_DEG:g} deg apart, beyond it not all: {fix}")


def run_demo(out: Path, scene: SceneOptions | None = None, options: RunOptions | None = None,
             progress: Progress | None = None) -> DemoResult:
    """Render into ``out/scene``, reconstruct into ``out/run``, write ``out/accuracy.json``."""
    out = Path(out)
    options = options or RunOptions()
    scene = scene or SceneOptions()
    check_image_scale(scene.image_scale)
    far_apart = check_arrangement(scene.num_rigs, scene.arc_deg)
    if far_apart:
        logger.warning("%s", far_apart)
    if (out / "accuracy.json").exists() and not options.overwrite:
        raise WorkspaceError(f"{out / 'accuracy.json'} already exists: pass --overwrite to replace the demo in {out}")
    if progress:
        progress("render", 0, 1)
    # without accuracy.json the demo never finished: its scene is rendered again, as the same command resumes (the
    # render replaces only the files its manifest lists and refuses a folder holding any other)
    dataset = render_dataset(out / "scene", scene, overwrite=True)
    if progress:
        progress("render", 1, 1)
    result = run(dataset.images, dataset.rigs, out / "run", dataset.scale, options, progress)
    accuracy = {"scene": asdict(scene), "timings_s": result.summary.timings_s, **score(result, dataset)}
    write_json_atomic(out / "accuracy.json", accuracy)
    return DemoResult(dataset, result, accuracy)
