"""Narrow observations from heads (rigsfm.run.narrow.heads) on a rendered crowd of 3D persons."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial import cKDTree

from rigsfm.run.checks.self_check import synchronised_frames
from rigsfm.run.narrow.heads import HeadMatches, decide_heads, match_heads
from rigsfm.run.options import NarrowMode, RunOptions
from rigsfm.run.pipeline import run
from rigsfm.synth.scene import SceneOptions

# 3D persons (heads at 1.5-1.9 m, occluding flat-shaded bodies) seen by 4 rigs over 135 deg.
PERSONS = SceneOptions(num_rigs=4, arc_deg=135.0, image_scale=0.5, seed=0, persons_per_m2=4.0)


def _scale_with_floor_bar(options: SceneOptions, path: Path) -> Path:
    """scale.yaml with a 2 m bar on the floor seen by the first two rigs (as a surveyor's marks: the crowd hides
    any bar the renderer would place), so the run finds the floor frame that heights need."""
    from rigsfm.synth.cameras import make_rigs
    from rigsfm.synth.dataset import _scale_yaml, choose_bar
    from rigsfm.synth.scene import build_arena

    rigs = make_rigs(options)
    bar = choose_bar(build_arena(options), rigs[0], rigs[1])
    assert bar is not None
    path.write_text(_scale_yaml(rigs, bar, rigs[0], rigs[1]))
    return path


@pytest.fixture(scope="module")
def persons_run(rendered, tmp_path_factory):
    dataset = rendered(PERSONS)
    root = tmp_path_factory.mktemp("narrow_heads")
    scale = _scale_with_floor_bar(PERSONS, root / "scale.yaml")
    return dataset, run(dataset.images, dataset.rigs, root / "auto", scale, RunOptions(narrow=NarrowMode.AUTO))


def _true_heads(dataset) -> dict[str, np.ndarray]:
    """image -> rows x, y, person of every head whose centre is inside it (persons/heads.csv)."""
    heads: dict[str, list] = {}
    with open(Path(dataset.root) / "persons" / "heads.csv", newline="") as f:
        for row in csv.DictReader(f):
            heads.setdefault(row["image"], []).append((float(row["x"]), float(row["y"]), int(row["person"])))
    return {name: np.asarray(rows) for name, rows in heads.items()}


def test_heads_match_across_views_and_turn_the_narrow_observations_on(persons_run):
    dataset, result = persons_run
    summary = json.loads(result.workspace.summary.read_text(encoding="utf-8"))
    record = summary["narrow_observations"]
    assert record["used"] and record["matched_by"] == "heads", record["reason"]
    assert record["head_persons"] >= 12 and record["observations_added"] > 0
    assert record["held_out_matches"] > 0  # every fifth person kept out of the adjustment
    # The heads matched on the delivered model (its bands) are mostly the same person's head in both views (the
    # nearest true head within 6 px).
    model = pycolmap.Reconstruction(str(result.workspace.sparse))
    poses = json.loads(result.workspace.narrow_poses.read_text(encoding="utf-8"))
    bands = {(p["i"], p["j"]): p["epipolar_band_95_px"] for p in poses["pairs"]}
    heads = match_heads(model, dataset.images, synchronised_frames(model), bands)
    assert decide_heads(heads)[0]
    truth = _true_heads(dataset)
    right = total = 0
    for pair in heads.pairs:
        if not pair.matches:
            continue
        ti, tj = truth[pair.i], truth[pair.j]
        di, ii = cKDTree(ti[:, :2]).query(pair.xy_i)
        dj, jj = cKDTree(tj[:, :2]).query(pair.xy_j)
        same = (di < 6) & (dj < 6) & (ti[ii, 2] == tj[jj, 2])
        right += int(same.sum())
        total += len(same)
    assert total >= 40 and right >= 0.8 * total, (right, total)


def test_auto_needs_enough_confident_persons():
    assert decide_heads(HeadMatches(candidates={"a": 40, "b": 40}, persons=3))[0] is False
    used, reason = decide_heads(HeadMatches(candidates={"a": 40, "b": 40}, persons=30))
    assert used and reason.startswith("heads usable: 30 persons")
