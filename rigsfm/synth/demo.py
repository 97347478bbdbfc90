"""``rigsfm demo``: render the built-in arena, run the pipeline on it, and score it against the truth.

The score compares the run with the ground truth and with the oracle (bundle adjustment started from
the true poses with the same observations and calibration file), i.e. the accuracy limit.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rigsfm.synth.truth import centre_errors_mm, compare_to_ground_truth, oracle
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import write_json_atomic
from rigsfm.run.pipeline import Progress, RunOptions, RunResult, load_inputs, run
from rigsfm.synth.dataset import SyntheticDataset, render_dataset
from rigsfm.synth.scene import SceneOptions

logger = logging.getLogger(__name__)


@dataclass
class DemoResult:
    dataset: SyntheticDataset
    run: RunResult
    accuracy: dict = field(default_factory=dict)


def score(result: RunResult, dataset: SyntheticDataset) -> dict:
    """Accuracy of a run on a rendered dataset, next to the oracle's."""
    truth = dataset.load_ground_truth()
    inputs = load_inputs(dataset.images, dataset.rigs, dataset.scale)
    limit = oracle(result.reconstruction, truth, inputs.rigs, inputs.scale)
    return {
        "narrow": compare_to_ground_truth(result.reconstruction, truth, "narrow"),
        "wide": compare_to_ground_truth(result.reconstruction, truth, "wide"),
        "narrow_centre_error_mm": centre_errors_mm(result.reconstruction, truth),
        "oracle_narrow": compare_to_ground_truth(limit, truth, "narrow"),
        "oracle_narrow_centre_error_mm": centre_errors_mm(limit, truth),
    }


def run_demo(out: Path, scene: SceneOptions | None = None, options: RunOptions | None = None,
             progress: Progress | None = None) -> DemoResult:
    """Render into ``out/scene``, reconstruct into ``out/run``, write ``out/accuracy.json``."""
    out = Path(out)
    options = options or RunOptions()
    scene = scene or SceneOptions()
    if (out / "accuracy.json").exists() and not options.overwrite:
        raise WorkspaceError(f"{out / 'accuracy.json'} already exists: pass --overwrite to replace the demo in {out}")
    if progress:
        progress("render", 0, 1)
    dataset = render_dataset(out / "scene", scene, overwrite=options.overwrite)
    if progress:
        progress("render", 1, 1)
    result = run(dataset.images, dataset.rigs, out / "run", dataset.scale, options, progress)
    accuracy = {"scene": asdict(scene), "timings_s": result.summary.timings_s, **score(result, dataset)}
    write_json_atomic(out / "accuracy.json", accuracy)
    return DemoResult(dataset, result, accuracy)
