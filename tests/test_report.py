"""report.html, `rigsfm view --screenshot` and `rigsfm export` on one rendered 3-rig scene run once.

Real clients read the outputs: headless Chromium (the report), Open3D (every Open3D file), Debian's colmap
3.8 (the COLMAP export); nerfstudio's camera convention is checked by projecting points with it.
"""

import html
import json
import subprocess

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import copy_run
from support import launch_chromium
from typer.testing import CliRunner

from rigsfm.cli import app
from rigsfm.core.errors import WorkspaceError
from rigsfm.inspect.export import export
from rigsfm.inspect.options import ExportFormat, ExportOptions
from rigsfm.inspect.viewer import NARROW_RGB, WIDE_RGB

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)

NAMES = sorted(f"rig0{i}/{s}/frame0000.png" for i in (1, 2, 3) for s in ("narrow", "wide"))


@pytest.fixture(scope="module")
def result(three_rig_run, tmp_path_factory):
    dataset, shared, _ = three_rig_run  # the session's run (conftest), copied: reports are rewritten in OUT
    out = copy_run(shared, tmp_path_factory.mktemp("report") / "out")
    return dataset, out, pycolmap.Reconstruction(out / "sparse")


def test_run_writes_report_with_bands(result):
    _, out, _ = result
    narrow = json.loads((out / "narrow_poses.json").read_text())
    assert "epipolar_band_95_px" in narrow["conventions"]
    for pair in narrow["pairs"]:
        assert 0.05 < pair["epipolar_band_95_px"] < 20.0
        near, far = pair["epipolar_band_depth_range_m"]
        assert 1.0 < near < far < 200.0  # the rigs are 15 m from the centre they look at
    page = (out / "report.html").read_text()
    assert "<script" not in page and 'src="http' not in page and 'href="http' not in page and "url(" not in page
    assert page.count('<img alt="epipolar check ') == 3  # one epipolar figure per narrow pair
    assert page.count('src="data:image/jpeg;base64,') == 3  # the epipolar figures are JPEG
    assert page.count('<img alt="reprojection errors of ') == 3  # one histogram per camera with observations
    assert f"{narrow['pairs'][0]['epipolar_band_95_px']:.3g}" in page
    # the uncertainty record: every narrow camera's sigmas and every pair's band, in summary.json and the report
    uncertainty = json.loads((out / "summary.json").read_text())["uncertainty"]
    # the default refines each rig's calibration the images inform and holds the others at rigs.yaml's values;
    # a network held entirely is the fixed-calibration adjustment
    decisions = json.loads((out / "summary.json").read_text())["calibration_decisions"]
    assert sorted(d["rig"] for d in decisions) == ["rig01", "rig02", "rig03"]
    held_all = all(d["held"] for d in decisions)
    assert (uncertainty["calibration"], uncertainty["covariance"]) == (("fixed", "consider") if held_all
                                                                       else ("refine", "posterior"))
    for d in decisions:
        assert html.escape(d["reason"]) in page
    assert uncertainty["bands"] == "sampled"  # three rigs: re-adjusted over calibration draws
    assert len(uncertainty["narrow"]) == 3 and len(uncertainty["pairs"]) == 3
    for name, sigmas in uncertainty["narrow"].items():
        assert 1.0 < sigmas["centre_sigma_mm"] < 200.0 and 0.01 < sigmas["rotation_sigma_deg"] < 1.0, name
        assert f"{sigmas['centre_sigma_mm']:.3g}" in page
    for pair in uncertainty["pairs"]:
        assert 0.0 <= pair["predicted_below_85"] <= 0.5


def test_report_opens_in_headless_chromium(result, tmp_path):
    import playwright.sync_api as playwright

    _, out, _ = result
    runner = CliRunner().invoke(app, ["report", str(out)])
    assert runner.exit_code == 0, runner.output
    messages = []
    with playwright.sync_playwright() as p:
        browser = launch_chromium(p)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.on("console", lambda m: messages.append(f"{m.type}: {m.text}") if m.type in ("error", "warning") else None)
        page.on("pageerror", lambda e: messages.append(str(e)))
        page.on("request", lambda r: messages.append(f"request {r.url}") if not r.url.startswith(("file:", "data:")) else None)
        page.goto((out / "report.html").as_uri())
        title = page.title()
        headings = page.locator("h2").all_inner_texts()
        pair_rows = page.locator("h2:text('Narrow camera pairs') + p + table tbody tr").count()
        figure_sizes = page.eval_on_selector_all("figure img", "els => els.map(e => [e.naturalWidth, e.naturalHeight])")
        page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
        browser.close()
    assert messages == []
    assert title.startswith("rigsfm report")
    assert {"Summary", "Reprojection error per camera", "Network (top view)", "Narrow camera pairs", "Uncertainty",
            "Epipolar check"} <= set(headings)
    assert pair_rows == 3
    assert len(figure_sizes) == 3 and all(w > 500 and h > 150 for w, h in figure_sizes)
    shot = cv2.imread(str(tmp_path / "report.png"))
    assert shot.shape[0] > 2000 and shot.std() > 20  # a long page with content, not a blank one


def test_view_screenshot_shows_both_frustums(result, tmp_path):
    _, out, _ = result
    path = tmp_path / "view.png"
    runner = CliRunner().invoke(app, ["view", str(out), "--screenshot", str(path)])
    assert runner.exit_code == 0, runner.output
    image = cv2.imread(str(path))[..., ::-1].reshape(-1, 3).astype(int)
    assert image.shape[0] == 1280 * 800
    for colour in (WIDE_RGB, NARROW_RGB):
        close = np.abs(image - 255 * np.array(colour)).max(axis=1) < 40
        assert close.sum() > 100, colour


def test_open3d_export_reads_back(result, tmp_path):
    import open3d as o3d

    _, out, rec = result
    dest = export(out, ExportOptions(format=ExportFormat.OPEN3D, dest=tmp_path / "o3d"))
    assert len(o3d.io.read_point_cloud(str(dest / "points.ply")).points) == rec.num_points3D()
    lines = o3d.io.read_line_set(str(dest / "frustums.ply"))
    assert len(lines.lines) >= 6 * 8  # 8 edges per frustum at least
    trajectory = o3d.io.read_pinhole_camera_trajectory(str(dest / "trajectory.json"))
    names = json.loads((dest / "cameras.json").read_text())["trajectory_entries"]
    assert sorted(names) == NAMES and len(trajectory.parameters) == 6
    for name, params in zip(names, trajectory.parameters):
        image = rec.find_image_with_name(name)
        camera = rec.cameras[image.camera_id]
        np.testing.assert_allclose(params.extrinsic[:3], image.cam_from_world().matrix(), atol=1e-9)
        k = params.intrinsic.intrinsic_matrix
        assert k[0, 2] == pytest.approx(camera.principal_point_x - 0.5) and k[0, 0] == pytest.approx(camera.focal_length_x)


def test_open3d_export_of_a_model_without_points(result, tmp_path, caplog):
    """Open3D neither writes nor reads a cloud of no points: the cameras are exported and the missing cloud said."""
    import open3d as o3d

    _, shared, rec = result
    out = copy_run(shared, tmp_path / "out")
    pointless = pycolmap.Reconstruction(out / "sparse")
    for point_id in list(pointless.point3D_ids()):
        pointless.delete_point3D(point_id)
    pointless.write_binary(str(out / "sparse"))
    dest = export(out, ExportOptions(format=ExportFormat.OPEN3D, dest=tmp_path / "o3d"))
    assert not (dest / "points.ply").exists() and "no 3D points" in caplog.text
    assert len(o3d.io.read_pinhole_camera_trajectory(str(dest / "trajectory.json")).parameters) == rec.num_reg_images()


def test_nerfstudio_export_says_where_images_are_missing(result, tmp_path, caplog):
    """transforms.json points at the run's images: an export made after they moved says so, not nerfstudio later."""
    _, shared, _ = result
    out = copy_run(shared, tmp_path / "out")
    summary = json.loads((out / "summary.json").read_text())
    summary["inputs"]["images"] = str(tmp_path / "moved")
    (out / "summary.json").write_text(json.dumps(summary))
    export(out, ExportOptions(format=ExportFormat.NERFSTUDIO, dest=tmp_path / "ns"))
    assert "lacks 6 of 6 image(s)" in caplog.text and "nerfstudio will not find them" in caplog.text


@pytest.mark.parametrize("fmt", ["colmap-bin", "colmap-txt"])
def test_colmap_export_opens_in_debian_colmap(result, tmp_path, fmt):
    _, out, rec = result
    runner = CliRunner().invoke(app, ["export", str(out), "--format", fmt, "--dest",
                                                                 str(tmp_path / "model")])
    assert runner.exit_code == 0, runner.output
    analysis = subprocess.run(["colmap", "model_analyzer", "--path", str(tmp_path / "model")], capture_output=True,
                              text=True, check=True)
    text = analysis.stdout + analysis.stderr
    assert "Registered images: 6" in text and f"Points: {rec.num_points3D()}" in text
    subprocess.run(["colmap", "model_converter", "--input_path", str(tmp_path / "model"), "--output_path",
                    str(tmp_path), "--output_type", "TXT"], capture_output=True, check=True)
    rows = [line.split() for line in (tmp_path / "images.txt").read_text().splitlines() if not line.startswith("#")]
    poses = {row[9]: [float(v) for v in row[1:8]] for row in rows if len(row) == 10}
    assert sorted(poses) == NAMES
    for name, (qw, qx, qy, qz, tx, ty, tz) in poses.items():  # colmap 3.8 wrote back what we exported
        image = rec.find_image_with_name(name)
        np.testing.assert_allclose([tx, ty, tz], image.cam_from_world().translation, atol=1e-6)
        np.testing.assert_allclose(pycolmap.Rotation3d(np.array([qx, qy, qz, qw])).matrix(),
                                   image.cam_from_world().rotation.matrix(), atol=1e-6)


def test_nerfstudio_transforms_project_like_colmap(result, tmp_path):
    dataset, out, rec = result
    dest = export(out, ExportOptions(format=ExportFormat.NERFSTUDIO, dest=tmp_path / "ns"))
    data = json.loads((dest / "transforms.json").read_text())
    assert np.allclose(data["applied_transform"], np.eye(4)[:3]) and (dest / data["ply_file_path"]).is_file()
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    for frame in data["frames"]:
        image = rec.find_image_with_name(frame["rigsfm_name"])
        assert frame["file_path"] == str((dataset.images / image.name).resolve())
        assert frame["camera_model"] == "OPENCV" and (frame["w"], frame["h"]) == (812, 617)
        c2w = np.array(frame["transform_matrix"])
        in_gl = (xyz - c2w[:3, 3]) @ c2w[:3, :3]  # OpenGL camera: x right, y up, looking down -z
        front = in_gl[:, 2] < 0
        u = frame["cx"] + frame["fl_x"] * in_gl[front, 0] / -in_gl[front, 2]  # nerfstudio: pixel centres +0.5
        v = frame["cy"] - frame["fl_y"] * in_gl[front, 1] / -in_gl[front, 2]
        pinhole = np.asarray(image.cam_from_world() * xyz[front]) @ np.asarray(
            rec.cameras[image.camera_id].calibration_matrix()).T
        np.testing.assert_allclose(np.column_stack([u, v]), pinhole[:, :2] / pinhole[:, 2:], atol=1e-6)


def test_json_export_and_overwrite_refused(result, tmp_path):
    _, out, rec = result
    dest = export(out, ExportOptions(format=ExportFormat.JSON, dest=tmp_path / "json"))
    images = json.loads((dest / "poses.json").read_text())["images"]
    assert sorted(i["name"] for i in images) == NAMES
    for entry in images:
        image = rec.find_image_with_name(entry["name"])
        np.testing.assert_allclose(entry["centre"], image.projection_center(), atol=1e-9)
    with pytest.raises(WorkspaceError, match="--overwrite"):
        export(out, ExportOptions(format=ExportFormat.JSON, dest=dest))


def test_commands_on_a_folder_without_result_fail_cleanly(tmp_path):
    for name, extra in (("report", []), ("view", ["--screenshot", "x.png"]), ("export", ["--format", "json"])):
        runner = CliRunner().invoke(app, [name, str(tmp_path), *extra])
        assert runner.exit_code == 1 and "run `rigsfm run" in runner.output, runner.output


def test_figures_are_capped_to_the_widest_and_narrowest_bands(result):
    """With fewer figures allowed than pairs: the widest bands first, then the narrowest; every pair is still
    listed, with whether (and why) it is drawn."""
    from rigsfm.core.summary import Summary
    from rigsfm.inspect.report.html import choose_figures, epipolar_section

    _, out, rec = result
    pairs = json.loads((out / "narrow_poses.json").read_text())["pairs"]
    bands = sorted(pairs, key=lambda p: p["epipolar_band_95_px"])
    assert choose_figures(pairs, max_figures=2) == {(bands[-1]["i"], bands[-1]["j"]): "widest band",
                                                    (bands[0]["i"], bands[0]["j"]): "narrowest band"}
    assert choose_figures(pairs, max_figures=3) == {(p["i"], p["j"]): "" for p in pairs}
    many = [dict(p, i=f"{p['i']}{k}") for k in range(10) for p in pairs]
    assert sorted(choose_figures(many, 12).values()).count("widest band") == 6
    page = epipolar_section(out, Summary.read(out / "summary.json"), rec, {"pairs": pairs}, max_figures=2)
    assert page.count('src="data:image/jpeg;base64,') == 2 and "2 of 3 pairs are drawn" in page
    assert page.count(">widest band</td>") == 1 and page.count(">narrowest band</td>") == 1 and page.count(">–</td>") == 1
    assert page.count("<tr>") == 1 + 3  # the table: header and every pair


def test_report_structure_top_view_bands_and_self_check(result):
    """The top view is drawn in the floor frame as the floor map is, with a ring per wide and a dot per narrow
    camera (their centres are centimetres apart); the pair bands sit under their own heading, before the refined
    calibration; a self-check in which no pair could be checked is one sentence, not a table of empty rows."""
    import dataclasses
    import re

    from rigsfm.core.summary import Summary, self_check_from_json
    from rigsfm.core.summary import describe_self_check as describe
    from rigsfm.inspect.report.html import self_check_section

    _, out, rec = result
    runner = CliRunner().invoke(app, ["report", str(out)])
    assert runner.exit_code == 0, runner.output
    page = (out / "report.html").read_text()
    top = page[page.index("<h2>Network (top view)</h2>"):page.index("<h2>World frame and floor map</h2>")]
    assert "as in the floor map" in top and "best-fit plane" not in top
    assert top.count('<circle class="wide"') == 3 and top.count('<circle class="narrow"') == 3
    uncertainty = page[page.index("<h2>Uncertainty</h2>"):page.index("<h2>Epipolar check</h2>")]
    headings = re.findall(r"<h3>(.*?)</h3>", uncertainty)
    assert headings[:2] == ["Epipolar band per pair", "Calibration held or refined"], headings
    bands = uncertainty[uncertainty.index("<h3>Epipolar band per pair</h3>"):
                        uncertainty.index("<h3>Calibration held or refined</h3>")]
    assert bands.count("<tr>") == 1 + 3 and "P(pair &lt; 85 % inside)" in bands

    summary = Summary.read(out / "summary.json")
    pair = {"frame": "frame0000.png", "i": "rig01/narrow/frame0000.png", "j": "rig02/narrow/frame0000.png",
            "band_px": 12.3, "matches": 0, "median_px": None, "p95_px": None, "within_band": None,
            "band_matches": 0, "measured_within_px": None, "verdict": "too few matches"}
    featureless = self_check_from_json({
        "frames": ["frame0000.png"], "guided_by": "epipolar band", "skipped": None, "seconds": 5.3,
        "settings": {"min_matches": 50, "wide_factor": 5.0, "keypoint_noise_px": 1.0}, "pairs": [pair] * 28})
    section = self_check_section(dataclasses.replace(summary, epipolar_self_check=featureless))
    assert "<table" not in section and "None of the 28 synchronised narrow pairs could be checked" in section
    assert describe(featureless).startswith("none of the 28 synchronised narrow pairs could be checked (0 matches "
                                            "in each, 50 needed): featureless narrow views")
    mixed = dataclasses.replace(featureless, pairs=[dataclasses.replace(featureless.pairs[0], matches=120, verdict="ok")]
                                + featureless.pairs[:2])
    assert "<table" in self_check_section(dataclasses.replace(summary, epipolar_self_check=mixed))
    assert describe(mixed) == "1 ok, 0 failed, 2 without verdict: 2 fewer than 50 matches (featureless views)"


def test_summary_reads_back_typed_and_writes_the_same_bytes(result, tmp_path):
    """summary.json read into its typed record (every section a record, read as attributes) writes out the same
    bytes; a summary of an older run without the world, self-check, --narrow or manual-matches sections reads with
    None for them, and the report and the terminal lines still come."""
    from rigsfm.cli.run import print_world
    from rigsfm.core.summary import NarrowObservationsSummary, SelfCheckSummary, Summary, WorldSummary

    _, out, _ = result
    text = (out / "summary.json").read_text()
    summary = Summary.from_json(json.loads(text))
    assert isinstance(summary.world, WorldSummary) and isinstance(summary.epipolar_self_check, SelfCheckSummary)
    assert isinstance(summary.narrow_observations, NarrowObservationsSummary)
    assert summary.epipolar_self_check.pairs[0].verdict and summary.world.frame in ("floor", "mapping")
    assert json.dumps(summary.to_json(), indent=2) + "\n" == text

    old = copy_run(out, tmp_path / "old")
    sections = ("world", "epipolar_self_check", "narrow_observations", "manual_matches")
    data = {k: v for k, v in json.loads(text).items() if k not in sections}
    (old / "summary.json").write_text(json.dumps(data, indent=2) + "\n")
    summary = Summary.read(old / "summary.json")
    assert summary is not None and all(getattr(summary, k) is None for k in sections)
    print_world(summary)  # nothing to print, no error
    runner = CliRunner().invoke(app, ["report", str(old)])
    assert runner.exit_code == 0, runner.output
    assert "Not run." in (old / "report.html").read_text()


def test_view_frustum_is_the_pyramid_alone():
    """A frustum in `rigsfm view` is the camera's pyramid: Open3D's camera axes (lines as long as the frustum is
    deep, out of the image sideways) are not drawn in the frustum's colour."""
    from rigsfm.inspect.viewer import frustum

    camera = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 3600.0, 1624, 1234)
    lines = frustum(camera, pycolmap.Rigid3d(), depth=2.0)
    points, ends = np.asarray(lines.points), np.asarray(lines.lines)
    assert len(ends) == 8
    assert np.allclose(points[np.unique(ends)][1:, 2], 2.0)  # every line ends at the centre or at the image plane
    assert np.abs(points[np.unique(ends)][:, :2]).max() < 0.5  # a narrow camera's pyramid is slim: no 2 m axes


def test_the_floor_line_names_metres_only_on_a_metric_result(monkeypatch):
    """Without a scale the floor frame's RMS and camera heights are in the mapper's units: the terminal said mm and m."""
    import io
    from types import SimpleNamespace

    from rich.console import Console

    import rigsfm.cli.run as cli_run
    from rigsfm.core.summary import WorldSummary

    floor = {"num_points": 812, "rms": 0.0042, "camera_height": {"min": 3.41, "max": 3.58}}
    lines = {}
    for units in ("metres", "arbitrary (not metric)"):
        out = io.StringIO()
        monkeypatch.setattr(cli_run, "console", Console(file=out, width=300))
        world = WorldSummary(asked="floor", frame="floor", units=units, floor=floor)
        cli_run.print_world(SimpleNamespace(world=world, epipolar_self_check=None, narrow_observations=None,
                                                 frame_offsets=None, replaced=None))
        lines[units] = out.getvalue()
    assert "RMS 4.2 mm; cameras 3.41-3.58 m above the floor" in lines["metres"]
    assert " mm" not in lines["arbitrary (not metric)"] and " m above" not in lines["arbitrary (not metric)"]
    assert "cameras 3.41-3.58 above the floor, in the mapper's units: not metric" in lines["arbitrary (not metric)"]


def test_the_uncertainty_section_names_millimetres_and_metres_only_on_a_metric_result():
    """Without a scale a narrow camera's centre sigma and the bands' analysis depths are in the mapper's units: the
    report's columns said mm and m (rec3 without scale.yaml: 'centre σ (mm) 21027.7', 'their depths in i (m)')."""
    from types import SimpleNamespace

    from rigsfm.core.summary import NarrowUncertaintySummary, PairBandSummary, UncertaintySummary
    from rigsfm.inspect.report.html import uncertainty_section

    u = UncertaintySummary(covariance="posterior", pixel_sigma_px=0.5,
                           narrow={"rig01/narrow/f0.png": NarrowUncertaintySummary(centre_sigma_mm=21027.7,
                                                                                   rotation_sigma_deg=0.1)},
                           pairs=[PairBandSummary(i="rig01/narrow/f0.png", j="rig02/narrow/f0.png", band_px=3.0,
                                                  points="depths", predicted_below_85=0.1)])
    pairs = [{"i": "rig01/narrow/f0.png", "j": "rig02/narrow/f0.png", "epipolar_band_depth_range_m": [0.5, 2.0]}]
    html = {metric: uncertainty_section({"metric": metric, "pairs": pairs},
                                        SimpleNamespace(uncertainty=u, calibration_decisions=[]))  # type: ignore[arg-type]
            for metric in (True, False)}
    assert "centre σ (mm)" in html[True] and "their depths in i (m)" in html[True] and "21027.7" in html[True]
    assert "centre σ (mm)" not in html[False] and "(m)" not in html[False], html[False]
    assert "centre σ (units)" in html[False] and '<td class="">21</td>' in html[False]
    assert "their depths in i (units)" in html[False]


def test_a_result_that_is_not_metric_writes_no_millimetre_keys_with_numbers():
    """summary.json's _mm keys hold millimetres or null: without a scale the centre sigma, its covariance and E^sl's
    translation change are in the mapper's unit, under _units keys (as scale.metres_per_mapping_unit is null), and
    the report reads them there (E^sl's columns said mm, the covariance was 1e6 times the unit's squares)."""
    from dataclasses import asdict
    from types import SimpleNamespace

    from rigsfm.core.summary import Summary
    from rigsfm.inspect.report.html import uncertainty_section
    from rigsfm.run.adjustment.narrow import NarrowUncertainty
    from rigsfm.run.adjustment.uncertainty import uncertainty_summary
    from rigsfm.run.options import Calibration

    cov = ((4.0e6, 0.0, 0.0), (0.0, 9.0e6, 0.0), (0.0, 0.0, 1.0e6))
    uncertainty = SimpleNamespace(
        covariance=None, floor="none", sampled=False, bands={}, bands_from="wide only",
        narrow={"rig01/narrow/f0.png": NarrowUncertainty(3741.7, 0.1, cov, ((0.01, 0, 0), (0, 0.01, 0), (0, 0, 0.01)))})
    result = SimpleNamespace(calibration=Calibration.FIXED)
    records = {metric: json.loads(json.dumps(asdict(uncertainty_summary(result, uncertainty, metric=metric))))
               for metric in (True, False)}  # type: ignore[arg-type]
    metric, arbitrary = (records[m]["narrow"]["rig01/narrow/f0.png"] for m in (True, False))
    assert metric["centre_sigma_mm"] == 3741.7 and metric["centre_covariance_mm2"][1][1] == 9.0e6
    assert metric["centre_sigma_units"] is None and metric["centre_covariance_units2"] is None
    assert arbitrary["centre_sigma_mm"] is None and arbitrary["centre_covariance_mm2"] is None
    assert arbitrary["centre_sigma_units"] == pytest.approx(3.7417) and arbitrary["centre_covariance_units2"][1][1] == 9.0

    summary = Summary.from_json({"uncertainty": {**records[False], "covariance": "posterior", "refined_calibration": {
        "rig01/narrow": {"narrow_from_wide_translation_change_mm": None, "narrow_from_wide_translation_sigma_mm": None,
                         "narrow_from_wide_translation_change_units": 0.0125,
                         "narrow_from_wide_translation_sigma_units": 0.0031, "observed": True}}}})
    html = uncertainty_section({"metric": False}, summary)
    assert "E^sl translation change (units)" in html and "(mm)" not in html, html
    assert ">0.0125<" in html and ">0.0031<" in html and ">3.74<" in html, html


def test_a_floor_from_the_markers_alone_is_said_so(monkeypatch):
    """A crowd hid the floor, so the floor frame came from the known-length bar's two ends: the terminal said
    '2 floor points, RMS 0.0 mm', a fit of two points that fit nothing."""
    import io
    from types import SimpleNamespace

    from rich.console import Console

    import rigsfm.cli.run as cli_run
    from rigsfm.core.summary import WorldSummary

    floor = {"num_points": 2, "rms": 0.0, "camera_height": {"min": 3.38, "max": 3.74},
             "points_by_source": {"sparse": 0, "matched": 0, "markers": 2}, "normal_sigma_deg": 0.45}
    out = io.StringIO()
    monkeypatch.setattr(cli_run, "console", Console(file=out, width=300))
    world = WorldSummary(asked="floor", frame="floor", units="metres", floor=floor)
    cli_run.print_world(SimpleNamespace(world=world, epipolar_self_check=None, narrow_observations=None,
                                        frame_offsets=None, replaced=None))
    line = out.getvalue()
    assert "RMS" not in line and "2 floor points" not in line
    assert "world: floor frame (from the 2 known-length end points alone, tilt sigma 0.45 deg; cameras 3.38-3.74 m " \
           "above the floor)" in line


def test_the_report_names_a_floor_from_the_markers_alone():
    """report.html labelled a floor made of the known-length bar's ends 'normal σ of the points' scatter (a lower
    bound)' with a 'fit residual RMS 0': its sigma is the cameras' up's (their rolls), its residual no fit's."""
    import pycolmap

    from rigsfm.inspect.report.html import world_section

    floor = {"found": True, "num_points": 2, "rms": 0.0, "camera_height": {"min": 3.38, "max": 3.74},
             "points_by_source": {"sparse": 0, "matched": 0, "markers": 2}, "normal_sigma_deg": 0.45,
             "marker_residuals": [0.0, 0.0], "matching": {"ran": True, "rounds": 1, "image_pairs": 12,
                                                          "matched_points": 55, "seconds": 16.1, "why": "none"}}
    world = {"frame": "floor", "asked": "floor", "units": "metres", "z_axis": "up", "origin": "o", "x_axis": "x",
             "floor": floor}
    section = world_section({"world": world}, pycolmap.Reconstruction())
    assert "points' scatter" not in section and "fit residual" not in section
    assert "the known-length markers alone" in section and "normal σ from the cameras' rolls" in section
