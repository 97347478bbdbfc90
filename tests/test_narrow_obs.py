"""Narrow observations (``rigsfm run --narrow auto|on|off``, rigsfm.run.narrow_obs) on rendered scenes."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from rigsfm.associate.sync import NOT_A_RECORDING, RigTiming, SyncCheck
from rigsfm.core.summary import BANDS_WIDE_ONLY, BANDS_WITH_NARROW
from rigsfm.run.narrow.observations import (
    MIN_PAIR_MATCHES,
    NarrowObservations,
    PairMatches,
    decide,
    describe_record,
)
from rigsfm.run.options import NarrowMode, RunOptions
from rigsfm.run.pipeline import run
from rigsfm.synth.scene import SceneOptions
from rigsfm.synth.truth import compare_to_ground_truth

# A flat crowd seen by 4 rigs over 90 deg: textured narrow views (the same scene as test_interrupt's).
CROWD = SceneOptions(num_rigs=4, arc_deg=90.0, textured_centre=True, image_scale=0.5, seed=0)


def _pair(signed: np.ndarray, tolerance: float = 6.0) -> PairMatches:
    n = len(signed)
    xy = np.c_[np.arange(n, dtype=float), np.zeros(n)]
    spread = 1.4826 * float(np.median(np.abs(signed - np.median(signed))))
    return PairMatches("f", "a", "b", xy, xy, np.zeros(n, bool), found=n, tolerance_px=tolerance, spread_px=spread)


def test_auto_needs_matches_concentrated_on_the_epipolar_lines():
    rng = np.random.default_rng(0)
    false = [_pair(rng.uniform(-6, 6, 40)) for _ in range(4)]  # evenly over the search band: chance matches
    true = [_pair(rng.normal(0, 0.8, 40)) for _ in range(4)]
    few = [_pair(rng.normal(0, 0.8, MIN_PAIR_MATCHES - 1)) for _ in range(4)]
    assert decide(NarrowMode.AUTO, false)[0] is False
    assert decide(NarrowMode.AUTO, few)[0] is False
    used, reason = decide(NarrowMode.AUTO, true)
    assert used and reason.startswith("the narrow images carry usable texture: 4 of 4")
    assert decide(NarrowMode.ON, false)[0] is True  # asked: used wherever there are matches


def test_a_search_of_whole_epipolar_lines_keeps_to_the_candidate_budget(rendered, monkeypatch):
    """Without a floor frame every narrow pair is searched along whole epipolar lines (a no-floor crowd: 0.5-0.9 M
    candidate pairs a pair, 26.5 s CPU for its 28 pairs). Beyond MAX_PAIR_CANDIDATES every k-th keypoint of i is
    searched, whole lines each, and a pair needs that share of MIN_PAIR_MATCHES; under it nothing changes."""
    from rigsfm.run.narrow import observations

    dataset = rendered(CROWD)
    model = dataset.load_ground_truth()
    compared = []

    def counted(fi, fj, a, b, *rest):
        compared.append(len(a))
        return guided(fi, fj, a, b, *rest)

    guided = observations.guided_matches
    monkeypatch.setattr(observations, "guided_matches", counted)
    monkeypatch.setattr(observations, "MAX_PAIR_CANDIDATES", 1 << 40)
    whole = observations.find_matches(model, dataset.images, floor_frame=False)
    assert all(p.searched == 1.0 for p in whole) and min(compared) > 20_000, compared
    budget = min(compared) // 4
    compared.clear()
    monkeypatch.setattr(observations, "MAX_PAIR_CANDIDATES", budget)
    thinned = observations.find_matches(model, dataset.images, floor_frame=False)
    assert compared and max(compared) <= budget, (compared, budget)
    assert all(p.searched < 0.5 for p in thinned if p.found), [p.searched for p in thinned]
    assert [p.tolerance_px for p in thinned] == [p.tolerance_px for p in whole]
    floor = observations.find_matches(model, dataset.images, floor_frame=True)  # far under it: unchanged
    assert all(p.searched == 1.0 for p in floor)


def test_a_thinned_search_needs_its_share_of_the_matches():
    rng = np.random.default_rng(0)
    pair = _pair(rng.normal(0, 0.8, MIN_PAIR_MATCHES // 4))
    assert not pair.textured
    pair.searched = 0.25
    assert pair.textured


def test_narrow_features_is_the_old_name_of_narrow_on():
    from typer.testing import CliRunner

    from rigsfm.cli import app

    result = CliRunner().invoke(app, ["run", "--help"])
    assert "--narrow " in result.output and "--narrow-features" not in result.output
    with pytest.raises(Exception, match="--narrow must be one of auto, on, off"):
        RunOptions(narrow="sometimes")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def crowd_runs(rendered, tmp_path_factory):
    dataset = rendered(CROWD)
    root = tmp_path_factory.mktemp("narrow_obs")
    return dataset, {mode: run(dataset.images, dataset.rigs, root / str(mode), dataset.scale,
                               RunOptions(narrow=mode)) for mode in (NarrowMode.OFF, NarrowMode.AUTO)}


def test_auto_uses_a_crowds_narrow_images_and_comes_closer_to_the_truth(crowd_runs):
    dataset, runs = crowd_runs
    truth = dataset.load_ground_truth()
    record = runs[NarrowMode.AUTO].summary.narrow_observations
    assert record is not None and record.asked == "auto" and record.used, record
    assert record.observations_added > 200 and record.held_out_matches > 30
    assert record.matched_by == "floor warp" and record.head_sigma_px is None  # every observation at the pooled noise
    # the held-out matches never entered the adjustment: they check it, and agree with its bands
    verdicts = [c.verdict for c in record.held_out_check]
    assert verdicts.count("ok") >= 0.75 * len(verdicts) > 0
    error = {mode: compare_to_ground_truth(r.reconstruction, truth, "narrow")["relative_rotation_deg"]["median"]
             for mode, r in runs.items()}
    assert error[NarrowMode.AUTO] < 0.8 * error[NarrowMode.OFF], error
    narrow_rows = runs[NarrowMode.AUTO].summary.reprojection_error
    assert all(row.observations > 0 for camera, row in narrow_rows.items() if camera.endswith("/narrow"))
    assert runs[NarrowMode.OFF].summary.narrow_observations is None  # off: the run of before


def test_auto_stays_off_on_featureless_narrow_views_and_changes_nothing(three_rig_run, tmp_path):
    dataset, out, output = three_rig_run  # the CLI's defaults: --narrow auto
    summary = json.loads((out / "summary.json").read_text())
    record = summary["narrow_observations"]
    assert record["asked"] == "auto" and record["used"] is False
    assert "no usable texture" in record["reason"] and "narrow observations not used (--narrow auto)" in output
    off = run(dataset.images, dataset.rigs, tmp_path / "off", dataset.scale, RunOptions(narrow=NarrowMode.OFF))
    poses = json.loads((out / "narrow_poses.json").read_text())
    poses_off = json.loads((off.workspace.narrow_poses).read_text())
    assert poses["narrow"] == poses_off["narrow"] and poses["pairs"] == poses_off["pairs"]


def test_the_delivered_bands_are_the_adjustment_with_narrow_observations(crowd_runs):
    """With the narrow observations used, narrow_poses.json's bands are those of the second adjustment (which the
    narrow images' points narrow: they fix E^sl and the narrow intrinsics), not the first one's (what ``off``
    delivers); they still hold the true correspondences of floor points (scored as benchmarks/trust.py does)."""
    from benchmarks.trust import score_bands

    dataset, runs = crowd_runs
    truth = dataset.load_ground_truth()
    bands = {}
    for mode, result in runs.items():
        poses = json.loads(result.workspace.narrow_poses.read_text())
        bands[mode] = {(p["i"], p["j"]): p["epipolar_band_95_px"] for p in poses["pairs"]}
    assert runs[NarrowMode.AUTO].summary.uncertainty.bands_from == "with narrow observations"
    assert runs[NarrowMode.OFF].summary.uncertainty.bands_from == "wide only"
    # summary.json's bands are narrow_poses.json's (one adjustment for both)
    assert {(p.i, p.j): p.band_px for p in runs[NarrowMode.AUTO].summary.uncertainty.pairs} == pytest.approx(
        bands[NarrowMode.AUTO], abs=1e-3)
    assert bands[NarrowMode.AUTO].keys() == bands[NarrowMode.OFF].keys() and bands[NarrowMode.AUTO]
    wide, final = np.median(list(bands[NarrowMode.OFF].values())), np.median(list(bands[NarrowMode.AUTO].values()))
    assert final < 0.5 * wide, (final, wide)
    rows = score_bands(runs[NarrowMode.AUTO].reconstruction, truth,
                       {k: SimpleNamespace(band_px=b, points=None, predicted_below_85=None, predicted_coverage=0.0)
                        for k, b in bands[NarrowMode.AUTO].items()})
    counted = sum(r["num_true_points"] for r in rows)
    coverage = sum(r["coverage"] * r["num_true_points"] for r in rows) / counted
    assert len(rows) >= 3 and coverage >= 0.9, rows
    # the held-out matches are judged against the delivered (narrower) band with their keypoint noise
    checks = runs[NarrowMode.AUTO].summary.narrow_observations.held_out_check
    assert checks and all(c.band_px == pytest.approx(bands[NarrowMode.AUTO][(c.i, c.j)], abs=1e-3) for c in checks)


def test_the_covariance_weighs_each_narrow_pair_by_its_own_noise(crowd_runs):
    """The covariance with narrow observations estimates each narrow pair's noise and correlation from the
    adjusted model's own epipolar distances (rigsfm.run.adjustment.correlated); a run without them has no narrow
    pair, so its covariance is the one of before."""
    from rigsfm.run.adjustment.correlated import narrow_pair_noise

    _, runs = crowd_runs
    found = {}
    for mode, result in runs.items():
        model = result.reconstruction
        narrow = {image.camera_id for image in model.images.values() if "/narrow/" in image.name}
        found[mode] = narrow_pair_noise(model, narrow)
    assert found[NarrowMode.OFF] == ([], {})
    pairs, by_point = found[NarrowMode.AUTO]
    assert len(pairs) >= 3 and len(by_point) >= sum(p.points for p in pairs)
    assert all(0.02 < p.sigma_px < 1.0 and 0.0 <= p.rho < 1.0 for p in pairs), pairs
    sigmas = [p.sigma_px for p in pairs]
    assert max(sigmas) > 1.5 * min(sigmas), pairs  # pairs differ in noise: one pooled sigma would not do


def test_heads_leave_the_delivered_bands_to_the_first_adjustment():
    """Only floor matches have a noise model in the covariance (rigsfm.run.adjustment.correlated): with heads as
    the narrow observations the bands delivered are the first adjustment's, as the record and summary.json say."""
    floor = NarrowObservations("auto", True, "textured")
    heads = NarrowObservations("auto", True, "heads", matched_by="heads")
    unused = NarrowObservations("auto", False, "no texture")
    assert floor.bands_from == BANDS_WITH_NARROW and floor.summary().bands == BANDS_WITH_NARROW
    assert heads.bands_from == BANDS_WIDE_ONLY and heads.summary().bands == BANDS_WIDE_ONLY
    assert unused.bands_from == BANDS_WIDE_ONLY and unused.summary().bands is None


def test_without_a_scale_the_line_says_how_the_registered_narrow_cameras_are_posed(tmp_path):
    """Printed after 'narrow 17/17 registered', the line must not call those poses unknown: they follow from the wide
    cameras through E^sl, without the narrow images' own matches."""
    from rigsfm.run.narrow.observations import describe_record
    from rigsfm.run.narrow.stage import narrow_observations

    model, record = narrow_observations(None, SimpleNamespace(metric=False), tmp_path, NarrowMode.AUTO)
    line = describe_record(record.summary())
    assert model is None and not record.used
    assert "unknown" not in line and "not metric" in line and "E^sl" in line, line


def test_a_rig_the_heads_name_off_in_time_is_warned_and_recorded():
    """The heads' timing check (rigsfm.run.narrow.timing) in the record: a rig named off in time gives associate's
    FRAMES NOT SYNCHRONISED line with run's consequence and the file line that pairs its frames, and summary.json
    keeps the check; a rig not told, or none named, warns nothing."""
    record = NarrowObservations("auto", True, "heads usable")
    assert record.warnings == [] and record.summary().head_frame_offsets is None
    record.head_timing = SyncCheck("check", frames=["f1.png", "f2.png"], search=1,
                                   rigs={"rig03": RigTiming("rig03/narrow", {-1: 90, 0: 28, 1: 25}, 1, 5.7),
                                         "rig05": RigTiming("rig05/narrow", {-1: 30, 0: 24, 1: 20}, None, 0.8),
                                         "rig01": RigTiming("rig01/narrow", {-1: 20, 0: 60, 1: 20}, 0, 0.0)})
    [warning] = record.warnings
    assert warning.startswith("FRAMES NOT SYNCHRONISED: rig03 is about +1 frame off (")
    assert "kept out of the narrow adjustment" in warning and "('rig03: 1')" in warning
    summary = record.summary().head_frame_offsets
    assert summary["named"] == {"rig03": 1} and summary["rigs"]["rig05"]["offset"] is None
    assert "heads' frame offsets (check): estimated rig03 +1 frame (rig05 not told) over 2 frame(s)" in \
        describe_record(record.summary())
    record.head_timing.rigs["rig03"].offset = None
    assert record.warnings == []
    for rig in record.head_timing.rigs.values():  # the crowd timed no rig: the terminal says it is unknown
        rig.offset = None
    assert "heads' frame offsets (check): not told" in describe_record(record.summary())
    record.head_timing = SyncCheck("check", skipped=NOT_A_RECORDING)  # one or two frames: nothing to say
    assert "frame offsets" not in describe_record(record.summary())
