"""rigsfm associate on a rendered crowd of 3D persons against the exact visible heads, and its bad inputs."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import _once, _shared_root
from typer.testing import CliRunner

from rigsfm.associate import AssociateOptions, associate_frames, from_arrays, load_run
from rigsfm.associate.evaluate import (
    make_detections,
    reliability,
    score_groups,
    true_heads,
    truth_from_run,
    visible_heads,
)
from rigsfm.associate.output import FRAME_FILES, LEGACY_MARKER, MANIFEST, cells_seen, check_destination
from rigsfm.associate.report import associate_report_section
from rigsfm.cli import app
from rigsfm.core.ground import footprint
from rigsfm.core.workspace import Workspace, model_fingerprint
from rigsfm.inspect.export import export
from rigsfm.inspect.options import ExportFormat, ExportOptions

sys.path.insert(0, str(Path(__file__).parent))
from bad_inputs_table import CASES, run_case

CHI2_3D_95 = 7.814727903251178
# Four rigs on a 120 degree arc, every narrow camera aimed near the centre of a 4 persons/m^2 crowd (~270 visible
# heads per narrow image, ~215 persons seen by two or more narrow cameras); the run finds the floor.
SCENE = dict(num_rigs=4, arc_deg=120.0, image_scale=0.5, seed=1, persons_per_m2=4.0, narrow_extra_pitch_deg=-4.0)


@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    """(dataset, out): the crowd rendered and run once per session."""
    from rigsfm.synth.dataset import render_dataset, scale_with_floor_bar
    from rigsfm.synth.scene import SceneOptions

    def make(root: Path):
        dataset = render_dataset(root / "scene", SceneOptions(**SCENE), overwrite=True)
        out = root / "out"
        scale = scale_with_floor_bar(dataset, root / "scale.yaml")  # a floor frame: heights above the floor
        result = CliRunner().invoke(app, ["run", str(dataset.images), "--rigs", str(dataset.rigs), "--scale",
                                          str(scale), "--out", str(out)])
        assert result.exit_code == 0, result.output
        return dataset.root, out

    return _once(_shared_root(tmp_path_factory), "associate_crowd", make)


def _detections(dataset: Path, out: Path, seed: int = 0):
    model = load_run(out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(dataset, "frame0000").items() if n in sizes}
    return model, make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=seed)


def _groups(frame) -> list[list[tuple[str, int]]]:
    return [[(frame.views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in frame.result.members]


def _errors(dataset: Path, out: Path, truth, frame) -> tuple[np.ndarray, np.ndarray]:
    """3D error (m, the truth's frame) of every right person and whether it lies in its 95 % ellipsoid."""
    r, t = truth_from_run(pycolmap.Reconstruction(str(out / "sparse")),
                          pycolmap.Reconstruction(str(dataset / "ground_truth")))
    heads = true_heads(dataset, 0)
    errors, inside = [], []
    for group, point, covariance in zip(_groups(frame), frame.result.points, frame.result.covariances):
        ids = {int(truth.person[a][b]) for a, b in group}
        if len(ids) == 1 and -1 not in ids:
            e = r @ point + t - heads[ids.pop()]
            errors.append(np.linalg.norm(e))
            inside.append(e @ np.linalg.solve(r @ covariance @ r.T, e) <= CHI2_3D_95)
    return np.array(errors), np.array(inside)


def test_association_against_the_truth_and_a_fixed_threshold(crowd, caplog):
    """On the run's poses the crowd is hard (the bands are ~10 px, heads ~25 px apart), yet rigsfm's association is
    far more precise than a fixed-threshold one; with the exact poses (the same bands) most pairs are right. On the
    run's poses most persons are wrong, and the frame says so."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    from associate import fixed_threshold

    from rigsfm.associate.pipeline import RunModel

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    with caplog.at_level("WARNING", logger="rigsfm.associate.pipeline"):
        frame = associate_frames(model, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0]
    warned = [r.getMessage() for r in caplog.records if "chance groupings" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("frame0000.png: only "), warned  # 11 of 222 on this crowd
    groups = _groups(frame)
    ours = score_groups(groups, truth)
    assert ours.true_persons > 150
    assert all(len({name for name, _ in g}) == len(g) for g in groups)  # one detection per view per person
    assert np.all((frame.result.points[:, 2] >= 1.0) & (frame.result.points[:, 2] <= 2.1))
    fixed = max((score_groups(fixed_threshold(model, truth.points, px), truth) for px in (2, 8, 32)),
                key=lambda s: s.pair_f1)
    assert ours.pair_precision > 5 * fixed.pair_precision and ours.pair_f1 > 3 * fixed.pair_f1, (ours, fixed)

    exact = pycolmap.Reconstruction(str(dataset / "ground_truth"))
    images = {im.name: im for im in exact.images.values() if im.name in model.images}
    posed = RunModel(images, model.bands, model.known, model.world, model.centre_sigma_m)
    caplog.clear()
    with caplog.at_level("WARNING", logger="rigsfm.associate.pipeline"):
        frame = associate_frames(posed, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0]
    assert not [r for r in caplog.records if "chance groupings" in r.getMessage()]  # 43 of 256 confident here
    scores = score_groups(_groups(frame), truth)
    assert scores.pair_precision > 0.35 and scores.pair_f1 > 0.25, scores
    heads = true_heads(dataset, 0)
    errors, inside = [], []
    for group, point, covariance in zip(_groups(frame), frame.result.points, frame.result.covariances):
        ids = {int(truth.person[a][b]) for a, b in group}
        if len(ids) == 1 and -1 not in ids:
            e = point - heads[ids.pop()]
            errors.append(np.linalg.norm(e))
            inside.append(e @ np.linalg.solve(covariance, e) <= CHI2_3D_95)
    assert len(errors) >= 10 and np.median(errors) < 0.03
    assert np.mean(inside) >= 0.9  # the reported covariance holds the error (the band is conservative here)


def test_reported_uncertainty_holds_the_run_s_error(crowd):
    """The run's pose errors are shared by every person (a centre sigma of a few centimetres here): the reported
    covariance carries them, so the 95 % ellipsoids hold the right persons' errors. The run delivers each narrow
    centre's 3x3 covariance (its trace the centre sigma's square): cameras on an arc at one height move more
    horizontally than vertically, and so do the persons' points (their vertical error is the smallest here), which
    a sigma per camera cannot say."""
    dataset, out = crowd
    narrow = json.loads((out / "summary.json").read_text())["uncertainty"]["narrow"]
    for name, entry in narrow.items():
        matrix = np.asarray(entry["centre_covariance_mm2"])
        assert matrix.shape == (3, 3) and np.allclose(matrix, matrix.T), name
        assert np.trace(matrix) == pytest.approx(entry["centre_sigma_mm"] ** 2, rel=1e-6), name
        assert np.all(np.linalg.eigvalsh(np.asarray(entry["rotation_covariance_deg2"])) >= -1e-12), name
    errors, inside = [], []
    for seed in range(3):
        model, truth = _detections(dataset, out, seed)
        frame = associate_frames(model, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0]
        e, i = _errors(dataset, out, truth, frame)
        errors += list(e)
        inside += list(i)
    assert len(errors) >= 5 and np.median(errors) < 0.15, errors
    assert np.mean(inside) >= 0.75, (errors, inside)
    assert len(model.centre_covariance_m2) == len(narrow)
    for name, covariance in model.centre_covariance_m2.items():  # the world's axes, the floor at z = 0
        assert covariance[2, 2] < (covariance[0, 0] + covariance[1, 1]) / 2, name
    # The same persons with a third of each trace on every axis instead: the 3x3 moves variance from the vertical to
    # the horizontal.
    model.centre_covariance_m2 = {}
    isotropic = associate_frames(model, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0].result
    assert np.array_equal(isotropic.members, frame.result.members)
    change = frame.result.covariances - isotropic.covariances
    assert np.all(change[:, 2, 2] < 0) and np.all(change[:, 0, 0] + change[:, 1, 1] > 0)


def test_the_crowd_gives_its_detection_probability_and_heights(crowd):
    """Not assumed: the detection probability and the persons' heights come from the frame's own persons (on the
    exact poses, where the association finds enough of them), and the association uses them."""
    from rigsfm.associate.pipeline import RunModel

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    exact = pycolmap.Reconstruction(str(dataset / "ground_truth"))
    images = {im.name: im for im in exact.images.values() if im.name in model.images}
    posed = RunModel(images, model.bands, model.known, model.world, model.centre_sigma_m)
    result = associate_frames(posed, from_arrays(truth.points), AssociateOptions(pixel_sigma=1.5))[0].result
    ids = np.concatenate(list(truth.person.values()))
    seen = np.bincount(ids[ids >= 0])
    # the persons detected in three views or more (taller heads hide less: ~8 cm above the crowd's mean here)
    heads = true_heads(dataset, 0)[: len(seen), 2][seen >= 3]
    assert result.detection_probability is not None and 0.4 < result.detection_probability < 0.95
    assert result.height_prior is not None, "too few confident persons to estimate the heights"
    mean, sigma = result.height_prior
    assert abs(mean - heads.mean()) < 0.05 and 0.03 < sigma < 0.25, (result.height_prior, heads.mean(), heads.std())
    given = associate_frames(posed, from_arrays(truth.points),
                             AssociateOptions(pixel_sigma=1.5, detection_probability=0.6, height_prior=(1.2, 0.1)))
    assert given[0].result.detection_probability == 0.6 and given[0].result.height_prior == (1.2, 0.1)


def test_reliability_bins_persons_by_confidence_and_counts_the_right_ones():
    """A person is right when every detection is one true person's (a false detection or a second person makes it
    wrong); the last bin holds a confidence of 1."""
    from rigsfm.associate.evaluate import SyntheticDetections

    truth = SyntheticDetections(points={"a": np.zeros((3, 2)), "b": np.zeros((3, 2))},
                                person={"a": np.array([0, 1, -1]), "b": np.array([0, 2, -1])})
    groups = [[("a", 0), ("b", 0)], [("a", 1), ("b", 1)], [("a", 2), ("b", 2)], [("a", 1)]]
    bins = reliability(groups, np.array([0.1, 0.3, 0.97, 1.0]), truth, (0.0, 0.5, 0.95, 1.0))
    assert bins == [{"bin": [0.0, 0.5], "persons": 2, "mean_confidence": 0.2, "right": 0.5},
                    {"bin": [0.95, 1.0], "persons": 2, "mean_confidence": 0.985, "right": 0.5}]


def test_the_report_does_not_show_the_persons_of_a_replaced_result(tmp_path):
    """After `rigsfm run --overwrite` (a new recording, rigs moved) report.html showed OUT/associate's persons,
    found with the replaced result's poses, as this result's."""
    workspace = Workspace(tmp_path)
    workspace.sparse.mkdir()
    (workspace.sparse / "images.bin").write_bytes(b"the model associated in")
    (workspace.associate / "frame0000").mkdir(parents=True)
    (workspace.associate / "frame0000" / "persons.json").write_text(
        json.dumps({"frame": "frame0000.png", "views": [], "persons": [], "unassigned": []}))
    (workspace.associate / ".rigsfm-associate.json").write_text(
        json.dumps({"written_by": "rigsfm associate", "model": model_fingerprint(workspace.sparse)}))
    assert "<td>frame0000.png</td>" in associate_report_section(tmp_path)
    (workspace.sparse / "images.bin").write_bytes(b"the model of a run --overwrite")
    section = associate_report_section(tmp_path)
    assert "<td>frame0000.png</td>" not in section and "earlier result" in section and "--overwrite" in section


def test_cli_writes_every_output_and_joins_back(crowd, tmp_path):
    dataset, out = crowd
    _, truth = _detections(dataset, out, seed=1)
    csv_path = tmp_path / "heads.csv"
    csv_path.write_text(truth.csv_text())
    dest = tmp_path / "persons"
    result = CliRunner().invoke(app, ["associate", str(out), str(csv_path), "--out", str(dest), "--pixel-sigma", "1.5"])
    assert result.exit_code == 0, result.output
    folder = dest / "frame0000"
    persons = len(json.loads((folder / "persons.json").read_text())["persons"])
    assert f"frame0000.png: {persons} persons from " in result.output, result.output
    for name in ("persons.csv", "persons.json", "floor.png", "density.csv", "density.png"):
        assert (folder / name).stat().st_size > 0, name
    data = json.loads((folder / "persons.json").read_text())
    lines = csv_path.read_text().splitlines()
    assert len(data["persons"]) > 30
    for person in data["persons"][:50]:
        for d in person["detections"]:  # the row and the text as given join back to the input
            image, x, y = lines[d["row"] - 1].split(",")
            assert (image, x, y) == (d["image"], d["x_text"], d["y_text"])
    density = np.loadtxt(folder / "density.csv", delimiter=",", skiprows=1)
    assert density[:, 4].sum() == len(data["persons"])
    # the grid: whole cells from the origin, over where two views can place a person; nan where fewer see
    assert np.allclose(density[:, :4], np.round(density[:, :4])) and (density[:, 6] >= 2).any()
    assert np.array_equal(np.isnan(density[:, 5]), density[:, 6] < 2)
    assert density[density[:, 6] >= 2, 4].sum() >= 0.9 * len(data["persons"])  # edge cells: a view sees part
    used = (density[:, 6] >= 2) | (density[:, 4] > 0)  # tight: every edge row and column holds such a cell
    for column, end in ((0, np.min), (2, np.max), (1, np.min), (3, np.max)):
        assert used[density[:, column] == end(density[:, column])].any()
    model = load_run(out)  # and it loses none of the cells two views see within the footprints' extent
    narrow = [model.images[n] for n in model.images if "narrow" in n]
    union = np.concatenate([footprint(image, 1.55).polygon for image in narrow])
    lo, hi = np.floor(union.min(axis=0)), np.ceil(union.max(axis=0))
    assert (cells_seen(narrow, (*lo, *hi), 1.0, 1.55) >= 2).sum() == (density[:, 6] >= 2).sum()
    again = CliRunner().invoke(app, ["associate", str(out), str(csv_path), "--out", str(dest)])
    assert again.exit_code == 1 and "--overwrite" in again.output
    # the manifest names the run's model the persons were found in (report.html shows them only beside it)
    assert json.loads((dest / ".rigsfm-associate.json").read_text())["model"] == model_fingerprint(out / "sparse")
    # report.html's section, where the association is in the workspace's default folder
    shutil.copytree(dest, tmp_path / "workspace" / "associate")
    section = associate_report_section(tmp_path / "workspace")
    confident = sum(p["confidence"] >= 0.5 for p in data["persons"])
    assert f"<td>frame0000.png</td><td>{len(data['persons'])}</td><td>{confident}</td>" in section
    assert section.count("data:image/png;base64,") == 2
    # --overwrite replaces the association's own files (one folder per frame), never the user's
    (folder / "notes.txt").write_text("mine")
    args = ["associate", str(out), str(csv_path), "--out", str(dest), "--pixel-sigma", "1.5", "--overwrite"]
    refused = CliRunner().invoke(app, args)
    assert refused.exit_code == 1 and "did not write (frame0000/notes.txt)" in refused.output, refused.output
    assert (folder / "notes.txt").read_text() == "mine"
    (folder / "notes.txt").unlink()
    replaced = CliRunner().invoke(app, args)
    assert replaced.exit_code == 0, replaced.output
    assert json.loads((folder / "persons.json").read_text()) == data
    manifest = json.loads((dest / MANIFEST).read_text())
    assert "frame0000/persons.json" in manifest["files"]
    (folder / "persons.csv").write_text("edited")  # refused before the association, not after it
    edited = CliRunner().invoke(app, args)
    assert edited.exit_code == 1 and "is not what an earlier association wrote there" in edited.output
    assert (folder / "persons.csv").read_text() == "edited"
    # an earlier version's output (a marker, no manifest) is recognised by its layout
    (dest / MANIFEST).unlink()
    (dest / LEGACY_MARKER).write_text("written by rigsfm associate\n")
    assert sorted(check_destination(dest, True).ours) == sorted(
        [LEGACY_MARKER, *(f"frame0000/{name}" for name in FRAME_FILES)])


def test_cli_radius_column_turns_the_size_cue_on_and_its_absence_changes_nothing(crowd, tmp_path):
    from rigsfm.associate.evaluate import true_head_radii

    dataset, out = crowd
    model = load_run(out)
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    heads = {n: v for n, v in visible_heads(dataset, "frame0000").items() if n in sizes}
    truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=1,
                            radii=true_head_radii(dataset, heads), size_noise=0.05)
    assert truth.radius is not None
    text = {n: [(f"{x:.3f}", f"{y:.3f}") for x, y in xy] for n, xy in truth.points.items()}
    sized = tmp_path / "sized.csv"
    sized.write_text("image,x,y,radius\n" + "".join(
        f"{n},{x},{y},{r:.3f}\n" for n in text for (x, y), r in zip(text[n], truth.radius[n])))
    plain = tmp_path / "plain.csv"
    plain.write_text(truth.csv_text())

    def persons(csv_path: Path, *extra: str) -> dict:
        dest = tmp_path / csv_path.stem
        result = CliRunner().invoke(app, ["associate", str(out), str(csv_path), "--out", str(dest),
                                          "--pixel-sigma", "1.5", *extra])
        assert result.exit_code == 0, result.output
        return json.loads((dest / "frame0000" / "persons.json").read_text())

    with_sizes, without = persons(sized, "--size-noise", "0.05"), persons(plain)
    assert with_sizes["size_cue"]["used"] and 0.08 < with_sizes["size_cue"]["head_radius_m"] < 0.14
    assert without["size_cue"] == {"used": False, "head_radius_m": None}
    # without radii the persons are the library's on the same points, as before the column existed
    points = {n: np.array([[float(x), float(y)] for x, y in rows]).reshape(-1, 2) for n, rows in text.items()}
    library = associate_frames(model, from_arrays(points), AssociateOptions(pixel_sigma=1.5))[0].result
    assert [p["position_m"] for p in without["persons"]] == [[round(float(c), 5) for c in p] for p in library.points]
    assert [p["position_m"] for p in with_sizes["persons"]] != [p["position_m"] for p in without["persons"]]


def test_empty_frame_gives_no_person(crowd, tmp_path):
    dataset, out = crowd
    model = load_run(out)
    names = sorted(n for n in model.images if n.endswith("frame0000.png"))
    frame = associate_frames(model, from_arrays({n: np.zeros((0, 2)) for n in names}), AssociateOptions())[0]
    assert len(frame.result) == 0 and frame.result.points.shape == (0, 3)
    csv_path = tmp_path / "empty.csv"
    csv_path.write_text("image,x,y\n" + "".join(f"{n},,\n" for n in names))
    result = CliRunner().invoke(app, ["associate", str(out), str(csv_path), "--out", str(tmp_path / "persons")])
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "persons" / "frame0000" / "persons.json").read_text())
    assert data["persons"] == [] and len(data["views"]) == len(names)


@pytest.mark.parametrize("case", [c for c in CASES if ("etection" in c.did or "associate" in c.did)
                                  and c.kept == "nothing is written"], ids=lambda c: c.did)
def test_bad_detections_are_refused_naming_the_row(case, tmp_path):
    code, line = run_case(case, tmp_path / "case")
    assert code == 1 and line.startswith("error: ")
    # the row, or the run / option at fault
    assert "line" in line or "floor" in line or "--poses-from" in line or "--heights" in line
    assert not (tmp_path / "case" / "persons").exists()


def test_a_folder_with_the_user_s_files_is_refused_untouched(tmp_path):
    case = next(c for c in CASES if c.did == "`associate --overwrite` into a folder with other files")
    code, line = run_case(case, tmp_path / "case")
    assert code == 1 and "holds files rigsfm did not write (notes.txt)" in line
    assert [p.name for p in (tmp_path / "case" / "persons").iterdir()] == ["notes.txt"]


def test_wildtrack_export_reads_and_projects_like_mvdet(crowd, tmp_path):
    """Read the export the way MVDet's Wildtrack loader does and project floor points like its
    get_imagecoord_from_worldcoord (support.mvdet_floor_pixels)."""
    from support import mvdet_floor_pixels, rigsfm_floor_pixels

    _, out = crowd
    dest = tmp_path / "wildtrack"
    result = CliRunner().invoke(app, ["export", str(out), "--format", "wildtrack", "--dest", str(dest), "--images"])
    assert result.exit_code == 0, result.output
    model = pycolmap.Reconstruction(str(out / "sparse"))
    narrow = {im.name.split("/")[0]: im for im in model.images.values() if "/narrow/" in im.name and im.has_pose}
    assert sorted(p.name for p in (dest / "calibrations" / "intrinsic_zero").iterdir()) == \
        [f"intr_{rig}.xml" for rig in sorted(narrow)]
    floor_m = np.array([[x, y] for x in np.linspace(-3, 3, 5) for y in np.linspace(-3, 3, 5)])
    for rig, image in narrow.items():
        mvdet = mvdet_floor_pixels(dest / "calibrations", rig, floor_m)
        # float32 rvec / tvec, as the loader reads them
        assert np.max(np.abs(mvdet - rigsfm_floor_pixels(image, floor_m))) < 0.05
        assert (dest / "Image_subsets" / rig / "frame0000.png").is_file()


def test_wildtrack_images_that_changed_since_the_run_are_named(crowd, tmp_path, caplog):
    """Undistorted copies of pictures the run was not made from pair new pixels with its calibration: said."""
    _, shared = crowd
    out = tmp_path / "out"
    shutil.copytree(shared, out)
    summary = json.loads((out / "summary.json").read_text())
    images = tmp_path / "images"
    shutil.copytree(summary["inputs"]["images"], images)
    summary["inputs"]["images"] = str(images)
    (out / "summary.json").write_text(json.dumps(summary))
    model = pycolmap.Reconstruction(str(out / "sparse"))
    name = sorted(im.name for im in model.images.values() if "/narrow/" in im.name and im.has_pose)[0]
    cv2.imwrite(str(images / name), cv2.imread(str(images / name))[::-1])
    export(out, ExportOptions(format=ExportFormat.WILDTRACK, dest=tmp_path / "wildtrack", images=True))
    assert f"1 narrow image(s) changed since the run ({name})" in caplog.text


def test_wildtrack_images_name_a_camera_that_lacks_a_frame(tmp_path, caplog):
    """MVDet-family loaders read every camera in every frame: a narrow image the run lacks (not given, or not
    registered) was left out of Image_subsets without a word."""
    import logging

    from rigsfm.inspect.camera_files import _warn_missing_views

    complete = [tmp_path / rig / f"frame000{k}.png" for rig in ("rig01", "rig02", "rig03") for k in (0, 1)]
    with caplog.at_level(logging.WARNING, logger="rigsfm.inspect.camera_files"):
        _warn_missing_views(complete, tmp_path)
        assert not caplog.records
        _warn_missing_views([p for p in complete if p.parts[-2:] != ("rig03", "frame0001.png")], tmp_path)
    (record,) = caplog.records
    assert "1 camera(s) lack frames the others have (rig03: frame0001.png)" in record.getMessage()


def _right_groups(frame, truth) -> np.ndarray:
    """The true persons seen in three or more views, as member rows of ``frame`` (the estimator's input)."""
    person = np.concatenate([truth.person[v.name] for v in frame.views])
    rows = []
    for p in np.unique(person[person >= 0]):
        idx = np.flatnonzero(person == p)
        if len(idx) >= 3:
            row = np.full(len(frame.views), -1)
            row[frame.view_of[idx]] = idx
            rows.append(row)
    return np.array(rows)


def _mean_residuals(frame, groups) -> np.ndarray:
    points, _ = frame.triangulate(groups)
    points, _ = frame.triangulate(groups, points)
    out = []
    for v, view in enumerate(frame.views):
        rows = np.flatnonzero(groups[:, v] >= 0)
        uv, _ = view.project(points[rows])
        out.append(np.mean(frame.uv[groups[rows, v]] - uv, axis=0))
    return np.array(out)


def test_view_shifts_from_right_groups_remove_the_run_s_pose_error(crowd):
    """Each view's pose error moves all its persons alike: from right groups the estimated shifts take the groups'
    per-view mean residual from pixels to a fraction of one, stay within the run's pose sigmas, and re-associating
    with the shifted views and their tightened bands is far more accurate than on the run's poses."""
    from dataclasses import replace

    from rigsfm.associate.frame import _Frame
    from rigsfm.associate.pipeline import frame_views
    from rigsfm.associate.shifts import _apply_correction, estimate_view_shifts
    from rigsfm.associate.solve import associate_views

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    detections = from_arrays(truth.points)
    (name, images), = detections.frames().items()
    options = AssociateOptions(pixel_sigma=1.5, self_calibration_rounds=0)
    views = frame_views(model, detections, name, images)
    frame = _Frame(views, options)
    groups = _right_groups(frame, truth)
    before = np.linalg.norm(_mean_residuals(frame, groups), axis=1)
    assert before.max() > 2.0, before  # the run's pose error, seen by the right groups
    correction = estimate_view_shifts(frame, groups, options)
    _apply_correction(views, correction, options)
    after = np.linalg.norm(_mean_residuals(_Frame(views, options), groups), axis=1)
    assert after.max() < 0.5, (before, after)
    for view in views:  # the crowd's correction is one the run's own uncertainty allows
        assert np.linalg.norm(view.shift_px) < 3.03 * view.band_sigma_px
        assert view.sigma_pose_px < view.band_sigma_px

    plain = associate_views(frame_views(model, detections, name, images), options)
    corrected = associate_views(views, replace(options, self_calibration_rounds=0))
    f1 = [score_groups([[(views[v].name, int(i)) for v, i in enumerate(m) if i >= 0] for m in r.members],
                       truth).pair_f1 for r in (plain, corrected)]
    assert f1[1] > 0.3 and f1[1] > 3 * f1[0], f1


def test_self_calibration_finds_shifts_put_into_the_views(crowd):
    """On the exact poses, each view's detections moved by a few pixels (the pose error of a view, as the run's
    bands allow it): with the run's bands the association alone is lost; the self-calibration finds the shifts
    from the crowd (up to the common shift the rigs' geometry leaves free) and the association recovers."""
    from rigsfm.associate.pipeline import RunModel, frame_views
    from rigsfm.associate.solve import associate_views

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    exact = pycolmap.Reconstruction(str(dataset / "ground_truth"))
    posed = RunModel({im.name: im for im in exact.images.values() if im.name in model.images}, model.bands,
                     model.known, model.world, model.centre_sigma_m)
    put = np.array([[0.0, 0.0], [0.0, 5.0], [0.0, -5.0], [0.0, 4.0]])  # vertical: these rigs' epipolar lines are
    names = sorted(truth.points)  # near horizontal, so the pairs see vertical shifts best
    detections = from_arrays({n: truth.points[n] + put[k] for k, n in enumerate(names)})
    (name, images), = detections.frames().items()
    f1, shifts = [], None
    for rounds in (0, 2):
        views = frame_views(posed, detections, name, images)
        result = associate_views(views, AssociateOptions(pixel_sigma=1.5, self_calibration_rounds=rounds))
        f1.append(score_groups([[(views[v].name, int(i)) for v, i in enumerate(m) if i >= 0]
                                for m in result.members], truth).pair_f1)
        shifts = np.array([v.shift_px for v in views])
    assert [v.name for v in views] == names
    found = shifts[:, 1] - shifts[:, 1].mean()
    assert np.max(np.abs(found - (put[:, 1] - put[:, 1].mean()))) < 1.5, shifts
    assert f1[1] > 0.25 and f1[1] > 3 * f1[0], f1


def _two_frames(dataset: Path, out: Path, images_root: Path | None = None):
    """(run, detections, truths, put): two frames of the crowd's persons (frame0001: other noise, misses and false
    detections) seen by the exact cameras, each narrow image's detections moved by its own pixel offset ``put`` (as
    in the test above), with the run's bands; ``images_root``: where both frames' images are, for the appearance."""
    import copy

    from rigsfm.associate.pipeline import RunModel

    model, first = _detections(dataset, out)
    _, second = _detections(dataset, out, seed=1)  # the same persons, other noise, misses and false detections
    exact = pycolmap.Reconstruction(str(dataset / "ground_truth"))
    images = {}
    for image in exact.images.values():
        if image.name in model.images:
            later = copy.copy(image)
            later.name = image.name.replace("frame0000", "frame0001")
            images[image.name], images[later.name] = image, later

    def both(name: str) -> list[str]:
        return [name, name.replace("frame0000", "frame0001")]

    bands = {(a, b): band for (i, j), band in model.bands.items() for a, b in zip(both(i), both(j))}
    centres = {n: sigma for name, sigma in model.centre_sigma_m.items() for n in both(name)}
    posed = RunModel(images, bands, set(images), model.world, centres, images_root=images_root)
    put = np.array([[0.0, 0.0], [0.0, 5.0], [0.0, -5.0], [0.0, 4.0]])
    names = sorted(first.points)
    points = {n: first.points[n] + put[k] for k, n in enumerate(names)}
    points.update({n.replace("frame0000", "frame0001"): second.points[n] + put[k] for k, n in enumerate(names)})
    return posed, points, (first, second), put


def _associate_two_frames(posed, points, monkeypatch) -> tuple[list, list[str]]:
    """``associate_frames`` on :func:`_two_frames`' frames, and the frame of each association it ran (the first view's
    name per call of ``_solve``)."""
    import rigsfm.associate.solve as solve

    solves: list[str] = []
    real = solve._solve
    monkeypatch.setattr(solve, "_solve", lambda views, options, *more, **given: solves.append(views[0].name)
                        or real(views, options, *more, **given))
    frames = associate_frames(posed, from_arrays(points), AssociateOptions(pixel_sigma=1.5, self_calibration_rounds=2))
    assert [f.frame for f in frames] == ["frame0000.png", "frame0001.png"]
    return frames, solves


def _pair_f1(frame, truth) -> float:
    """A frame's pairwise F1 against the truth of :func:`_two_frames` (named by frame0000's images)."""
    return score_groups([[(frame.views[v].name.replace("frame0001", "frame0000"), int(i))
                          for v, i in enumerate(m) if i >= 0] for m in frame.result.members], truth).pair_f1


def test_shifts_carry_to_the_next_frame(crowd, monkeypatch):
    """A static rig's pose error is the same in every frame: the shifts the crowd gives the first frame carry to the
    next frame's images of the same cameras, which are associated once (no self-calibration of their own), as well
    as the first, and pool their own groups into the shifts."""
    dataset, out = crowd
    posed, points, truths, put = _two_frames(dataset, out)
    frames, solves = _associate_two_frames(posed, points, monkeypatch)
    assert sum("frame0000" in n for n in solves) >= 3 and sum("frame0001" in n for n in solves) == 1, solves
    f1 = [_pair_f1(frame, truth) for frame, truth in zip(frames, truths)]
    assert f1[0] > 0.25 and f1[1] > 0.8 * f1[0], f1
    for view in frames[1].views:
        assert view.shift_sigma_px is not None
    shifts = [np.array([v.shift_px[1] for v in f.views]) for f in frames]
    assert np.max(np.abs((shifts[1] - shifts[1].mean()) - (put[:, 1] - put[:, 1].mean()))) < 1.5, shifts
    # frame0001's record (its persons.json) holds the shifts its persons were found with, frame0000's; its views
    # go on with the shifts refined from its own persons
    for v0, v1 in zip(frames[0].views, frames[1].views):
        assert np.array_equal(frames[1].result.shift_px[v1.name], frames[0].result.shift_px[v0.name])
    assert any(not np.array_equal(frames[1].result.shift_px[v.name], v.shift_px) for v in frames[1].views)


def test_a_run_without_bands_is_named(crowd, caplog):
    """A run whose uncertainty failed has no bands: the association would see the pixel noise only and lose most
    persons without a word, so it says so."""
    import logging

    from rigsfm.associate.pipeline import RunModel, frame_views

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    detections = from_arrays(truth.points)
    (name, images), = detections.frames().items()
    with caplog.at_level(logging.WARNING, logger="rigsfm.associate.pipeline"):
        frame_views(model, detections, name, images)
        assert "no epipolar band" not in caplog.text
        bare = RunModel(model.images, {}, model.known, model.world, model.centre_sigma_m)
        frame_views(bare, detections, name, images)
    assert "no epipolar band" in caplog.text and "re-run `rigsfm run`" in caplog.text


def test_the_terminal_names_each_frame_or_summarises_the_rest(tmp_path):
    """`rigsfm associate`'s lines: every frame where at most one more than the shown would be summarised (a
    'summary' of one frame said '1 more frames: 498 persons (median), 498-498'), the rest in one line beyond."""
    from rigsfm.cli.associate import frame_lines, written_frames

    def write(count: int) -> Path:
        dest = tmp_path / f"dest{count}"
        for k in range(count):
            folder = dest / f"frame{k:04d}"
            folder.mkdir(parents=True)
            persons = [{"detections": [{"image": "rig01/narrow/a.png"}]} for _ in range(10 + k)]
            (folder / "persons.json").write_text(json.dumps(
                {"frame": f"frame{k:04d}.png", "persons": persons, "unassigned": [{"image": "x"}] * 2}))
        return dest

    assert frame_lines(written_frames(write(4))) == [f"frame{k:04d}.png: {10 + k} persons from {10 + k} of {12 + k} detections"
                                     for k in range(4)]
    lines = frame_lines(written_frames(write(6)))
    assert len(lines) == 4 and lines[-1] == "... 3 more frames: 14 persons (median), 13-15", lines


def test_frames_the_run_was_not_given_take_the_poses_of_one_of_its_frames(crowd, tmp_path):
    """A recording calibrated once: ``--poses-from FRAME`` lends that frame's narrow poses and bands to frames the
    run was not given (static rigs), and such a frame's persons are those the same detections give in the run's own
    frame. Without it such a frame is refused with the option named; a FRAME the run lacks is refused with its
    frames; nothing is written either time."""
    from rigsfm.associate import associate

    dataset, out = crowd
    _, truth = _detections(dataset, out)
    rows = "image,x,y\n" + "".join(f"{name},{x},{y}\n" for name, xy in truth.points.items() for x, y in xy)
    (tmp_path / "own.csv").write_text(rows)
    (tmp_path / "later.csv").write_text(rows.replace("frame0000", "frame0007"))
    runner = CliRunner()
    refused = runner.invoke(app, ["associate", str(out), str(tmp_path / "later.csv"), "--out", str(tmp_path / "no")])
    assert refused.exit_code == 1 and "was not given this frame" in refused.output \
        and "--poses-from" in refused.output, refused.output
    unknown = runner.invoke(app, ["associate", str(out), str(tmp_path / "later.csv"), "--out", str(tmp_path / "no"),
                                  "--poses-from", "frame0003.png"])
    assert unknown.exit_code == 1 and "its frames: 'frame0000.png'" in unknown.output, unknown.output
    bare = runner.invoke(app, ["associate", str(out), str(tmp_path / "later.csv"), "--out", str(tmp_path / "no"),
                               "--poses-from", "frame0000"])  # without its extension: the frame is named
    assert bare.exit_code == 1 and "(did you mean 'frame0000.png'?)" in bare.output, bare.output
    assert not (tmp_path / "no").exists()
    geometry = dict(pixel_sigma=1.5, appearance=False)  # the later frame's images are not beside the run's
    own = associate(out, tmp_path / "own.csv", AssociateOptions(out=tmp_path / "own", **geometry))
    lent = associate(out, tmp_path / "later.csv",
                     AssociateOptions(out=tmp_path / "lent", poses_from="frame0000.png", **geometry))
    first = json.loads((own / "frame0000" / "persons.json").read_text())
    later = json.loads((lent / "frame0007" / "persons.json").read_text())
    assert first["poses_from"] is None and later["poses_from"] == "frame0000.png"
    workspace = tmp_path / "workspace"  # report.html's table says which frame's poses each frame took
    workspace.mkdir()
    shutil.copytree(lent, workspace / "associate")
    assert "<td>lent by frame0000.png</td></tr>" in associate_report_section(workspace)
    shutil.copytree(own, workspace / "associate", dirs_exist_ok=True)
    assert "<td>its own</td></tr>" in associate_report_section(workspace)
    assert len(first["persons"]) > 100
    assert json.dumps(later["persons"]).replace("frame0007", "frame0000") == json.dumps(first["persons"])


def test_a_frame_the_run_was_given_and_did_not_register_is_refused_even_with_poses_lent(tmp_path):
    """The run tried such a frame and found no pose for it (a rig moved? images that do not match?): lending another
    frame's poses would hide that, so ``--poses-from`` lends only to frames the run was never given."""
    from rigsfm.associate.detections import read_detections
    from rigsfm.core.errors import InputError

    path = tmp_path / "heads.csv"
    path.write_text("image,x,y\nrig01/narrow/f0.png,10,20\nrig01/narrow/f1.png,10,20\nrig01/narrow/f2.png,10,20\n")
    sizes, known = {"rig01/narrow/f0.png": (64, 48)}, {"rig01/narrow/f0.png", "rig01/narrow/f1.png"}
    with pytest.raises(InputError, match=r"line 3: image 'rig01/narrow/f1.png': the run registered no model"):
        read_detections(path, sizes, known, {"rig01/narrow": (64, 48)})
    path.write_text("image,x,y\nrig01/narrow/f0.png,10,20\nrig01/narrow/f2.png,10,20\nrig01/narrow/f3.png,70,20\n")
    with pytest.raises(InputError, match=r"line 4: \(70, 20\) lies outside 'rig01/narrow/f3.png' \(64 x 48 px"):
        read_detections(path, sizes, known, {"rig01/narrow": (64, 48)})  # checked against the lent camera's size
    path.write_text("image,x,y\nrig01/narrow/f0.png,10,20\nrig01/narrow/f2.png,10,20\n")
    assert sorted(read_detections(path, sizes, known, {"rig01/narrow": (64, 48)}).images) == [
        "rig01/narrow/f0.png", "rig01/narrow/f2.png"]


def test_a_narrow_image_missing_from_a_frame_of_the_run_is_named_as_such(tmp_path):
    """A recording whose rig03 lacks one narrow image: the run was given that frame (rig03's wide image), so its
    detections there are refused as a narrow image it was not given, not as a frame it was not given; and a
    --poses-from frame without rig03's narrow image cannot lend rig03 a pose, which says so and names a frame that
    can, where it used to call the image not one of the run's ('check the name')."""
    from rigsfm.associate.detections import read_detections
    from rigsfm.core.errors import InputError

    path = tmp_path / "heads.csv"
    sizes = {"rig01/narrow/f0.png": (64, 48), "rig03/narrow/f0.png": (64, 48), "rig01/narrow/f1.png": (64, 48)}
    known = {*sizes, "rig01/wide/f0.png", "rig03/wide/f0.png", "rig01/wide/f1.png", "rig03/wide/f1.png"}
    path.write_text("image,x,y\nrig01/narrow/f1.png,10,20\nrig03/narrow/f1.png,10,20\n")
    with pytest.raises(InputError, match=r"line 3: image 'rig03/narrow/f1.png': the run was given this frame without "
                                         r"this narrow image \(only its wide image\), so it has no pose for it; .*"
                                         r"--poses-from FRAME"):
        read_detections(path, sizes, known)
    path.write_text("image,x,y\nrig01/narrow/f2.png,10,20\nrig03/narrow/f2.png,10,20\n")
    with pytest.raises(InputError, match=r"line 2: image 'rig01/narrow/f2.png': the run was not given this frame"):
        read_detections(path, sizes, known)
    with pytest.raises(InputError, match=r"line 3: image 'rig03/narrow/f2.png': the run was given this frame without "
                                         r"rig03's images, so"):  # rig03 lacks a frame the others have
        read_detections(path, {**sizes, "rig01/narrow/f2.png": (64, 48)}, {*known, "rig01/wide/f2.png"})
    lender = {"rig01/narrow": (64, 48)}  # f1's registered narrow cameras
    with pytest.raises(InputError, match=r"line 3: image 'rig03/narrow/f2.png': the run registered no narrow image of "
                                         r"rig03 in --poses-from's frame 'f1.png', so it has no pose to lend to this "
                                         r"one; pass a frame where it did \('f0.png'\)"):
        read_detections(path, sizes, known, lender, "f1.png")
    assert sorted(read_detections(path, sizes, known, {**lender, "rig03/narrow": (64, 48)}, "f0.png").images) == [
        "rig01/narrow/f2.png", "rig03/narrow/f2.png"]


def test_a_frame_of_the_run_lacking_a_narrow_image_is_not_counted_as_a_frame_it_was_not_given(tmp_path):
    """A recording whose rig03 lacks its narrow image of f1 (the run registered f1's other narrow images): with
    --poses-from f0 only rig03's view of f1 takes f0's pose. The terminal and report.html used to call f1 a frame the
    run was not given, 'lent by f0.png' as a whole; they now say which views took f0's poses (persons.json:
    ``lent_views``). An earlier version's persons.json (no ``lent_views``) lent to every view."""
    from rigsfm.associate.report import poses_note
    from rigsfm.cli.associate import lent_lines, written_frames

    views = [f"rig0{r}/narrow/f{{}}.png" for r in (1, 2, 3)]
    frames = {"f0": (None, []), "f1": ("f0.png", [views[2].format(1)]), "f2": ("f0.png", [v.format(2) for v in views]),
              "f3": ("f0.png", None)}
    for frame, (poses_from, lent) in frames.items():
        data = {"frame": f"{frame}.png", "views": [v.format(frame[1]) for v in views], "poses_from": poses_from,
                "persons": [], "unassigned": []}
        if lent is not None:
            data["lent_views"] = lent
        (tmp_path / frame).mkdir()
        (tmp_path / frame / "persons.json").write_text(json.dumps(data))
    written = written_frames(tmp_path)
    assert [poses_note(json.loads((tmp_path / f / "persons.json").read_text())) for f in frames] == [
        "its own", "1 of 3 views lent by f0.png, the others its own", "lent by f0.png", "lent by f0.png"]
    assert lent_lines(written, "f0.png", Path("out")) == [
        "2 frame(s) the run was not given: associated with the narrow poses of its frame f0.png (static rigs; "
        "`rigsfm track out IMAGES` tells whether a rig moved)",
        "1 frame(s) of the run without some of their narrow images (e.g. f1.png: 'rig03/narrow/f1.png'): those views "
        "took the narrow poses of its frame f0.png, the others their own"]


def test_associate_frames_lends_poses_to_the_views_a_frame_of_the_run_lacks(crowd):
    """The run's frame f1 with rig04's narrow image missing (here: the crowd's frame0000 renamed, without rig04's):
    --poses-from frame0000.png lends rig04's pose to its view of f1 alone (``lent_views``), and the frame's persons
    are those of frame0000 (the same detections, the same poses)."""
    from rigsfm.associate.pipeline import with_stand_ins

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    own = {n: xy for n, xy in truth.points.items()}
    later = {n.replace("frame0000", "frame0001"): xy for n, xy in own.items()}
    lacking = "rig04/narrow/frame0001.png"
    # the run as if it had registered frame0001 too, but for rig04's narrow image (its wide image given)
    given = with_stand_ins(model, [n for n in later if n != lacking], "frame0000.png")
    given = dataclasses.replace(given, stand_ins={}, known=given.known | set(given.images) | {
        "rig04/wide/frame0001.png"})
    lent = with_stand_ins(given, list(later), "frame0000.png")
    options = AssociateOptions(pixel_sigma=1.5, appearance=False, walk_m=None)
    [first] = associate_frames(lent, from_arrays(own), options)
    [second] = associate_frames(lent, from_arrays(later), options)
    assert first.poses_from is None and first.lent_views == ()
    assert second.poses_from == "frame0000.png" and second.lent_views == (lacking,)
    assert len(first.result) > 100
    assert _groups(second) == [[(n.replace("frame0000", "frame0001"), i) for n, i in g] for g in _groups(first)]


@pytest.mark.parametrize("dest, reason", [
    ("out", "is the workspace or a folder that holds it"), (".", "is the workspace or a folder that holds it"),
    ("out/sparse", "is inside the workspace's own sparse/ folder"), ("out/export", "is inside the workspace's own export/"),
    ("out/track/persons", "is inside the workspace's own track/ folder")])
def test_associate_out_is_refused_in_the_workspaces_own_folders(tmp_path, monkeypatch, dest, reason):
    """--out OUT was refused as holding 'files rigsfm did not write' (.rigsfm-workspace, colmap.log: rigsfm's),
    and --out OUT/export or OUT/track, not there yet, took the persons among the other commands' outputs; each is now
    refused with its reason and the default named, before anything is read or written."""
    from rigsfm.associate import associate
    from rigsfm.core.errors import InputError

    monkeypatch.chdir(tmp_path)
    (tmp_path / "out" / "sparse").mkdir(parents=True)
    (tmp_path / "out" / "colmap.log").write_text("")
    (tmp_path / "heads.csv").write_text("image,x,y\nrig01/narrow/f0.png,10,20\n")
    with pytest.raises(InputError, match=f"--out '{dest}' {reason}.*out/associate"):
        associate(Path("out"), Path("heads.csv"), AssociateOptions(out=Path(dest)))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["colmap.log", "sparse"]


def test_frames_warn_once_a_kind_with_the_frames_named(crowd, caplog):
    """A CSV of three frames: one of four views with few confident persons, then two of two views each (no person
    there can be confirmed by a third view: said, not silence). Each kind of warning is said once, naming its
    frames."""
    import logging

    from rigsfm.associate.pipeline import with_stand_ins

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    cameras = sorted({n.split("/")[0] for n in truth.points})
    kept = {"frame0000": cameras, "frame0001": cameras[:2], "frame0002": cameras[2:]}
    points = {n.replace("frame0000", frame): xy for frame, rigs in kept.items() for n, xy in truth.points.items()
              if n.split("/")[0] in rigs}
    lent = with_stand_ins(model, [n for n in points if n not in model.images], "frame0000.png")
    with caplog.at_level(logging.WARNING, logger="rigsfm.associate.pipeline"):
        frames = associate_frames(lent, from_arrays(points), AssociateOptions(pixel_sigma=1.5, appearance=False))
    assert [len(f.views) for f in frames] == [4, 2, 2]
    chance = [r.getMessage() for r in caplog.records if "chance groupings" in r.getMessage()]
    two = [r.getMessage() for r in caplog.records if "two narrow views only" in r.getMessage()]
    assert len(chance) == 1 and chance[0].startswith("frame0000.png: only "), chance
    assert len(two) == 1 and two[0].startswith("2 frames (frame0001.png: "), two
    assert "frame0002.png: " in two[0] and "frame0000" not in two[0], two


def test_the_library_says_once_that_lent_frames_have_no_images(crowd, caplog):
    """associate_frames (the library call, as the benchmarks use it) says that a lent frame's images are not beside
    the run's, so its views have no appearance: once, though a command associates a recording again."""
    import logging

    from rigsfm.associate.pipeline import with_stand_ins

    dataset, out = crowd
    model, truth = _detections(dataset, out)
    points = {**truth.points, **{n.replace("frame0000", "frame0001"): xy for n, xy in truth.points.items()}}
    lent = with_stand_ins(model, [n for n in points if n not in model.images], "frame0000.png")
    options = AssociateOptions(pixel_sigma=1.5)
    with caplog.at_level(logging.WARNING, logger="rigsfm.associate.pipeline"):
        for _ in range(2):
            associate_frames(lent, from_arrays(points), options)
    said = [r.getMessage() for r in caplog.records if "not beside its images" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith(f"{len(truth.points)} narrow image(s) of the frames"), said


def test_a_kind_of_frame_warning_is_said_once_naming_its_frames(caplog):
    """Frames 0 and 1 of a CSV both with few confident persons: one warning naming both, not one a frame."""
    import logging

    from rigsfm.associate.pipeline import FrameNotes

    notes = FrameNotes(few_confident=[("frame0000.png", 9, 172), ("frame0001.png", 12, 180)])
    with caplog.at_level(logging.WARNING, logger="rigsfm.associate.pipeline"):
        notes.say()
    [message] = [r.getMessage() for r in caplog.records]
    assert message.startswith("2 frames (frame0000.png: 9 of 172 persons, frame0001.png: 12 of 180 persons): only "
                              "those are seen by three or more views"), message


def test_views_lent_poses_after_a_tracked_move_are_named(tmp_path):
    """`rigsfm track` found rig02 moved at f3; `associate --poses-from f0` then lent f0's pose to rig02's views of
    f3-f5 without a word (the docs said nothing checks that the rigs stayed put, while OUT/track said they had not)."""
    from bad_inputs_table import workspace as small_workspace

    from rigsfm.associate.pipeline import lent_after_moves

    out = small_workspace(tmp_path)
    ws = Workspace(out)
    lent = [f"rig{r:02d}/narrow/f{k}.png" for r in (1, 2) for k in (1, 2, 3, 4, 5)]
    assert lent_after_moves(ws, lent) is None  # nothing tracked
    step = {"frame": "f3.png", "rotation_deg": 0.3, "translation_mm": 20.0}
    poses = {"reference": {"fingerprint": model_fingerprint(out / "sparse")},
             "rigs": {"rig01": {"verdict": {"verdict": "shaking", "steps": []}},
                      "rig02": {"verdict": {"verdict": "moved", "steps": [step]}}}}
    ws.track.poses_json.parent.mkdir(parents=True)
    ws.track.poses_json.write_text(json.dumps(poses))
    warning = lent_after_moves(ws, lent)
    assert warning is not None and warning.startswith("LENT AFTER A MOVE: `rigsfm track` found rig02 moved (")
    assert "(rig02: 3 frame(s) from f3.png, its step at f3.png)" in warning and "rig01" not in warning
    assert lent_after_moves(ws, [n for n in lent if not n.startswith("rig02")]) is None
    poses["reference"]["fingerprint"] = "another model"  # a series of a replaced result: not this model's
    ws.track.poses_json.write_text(json.dumps(poses))
    assert lent_after_moves(ws, lent) is None


def test_a_frame_paired_by_time_is_not_called_a_frame_of_the_run(tmp_path):
    """With --frame-offsets (rig03 +1) and --poses-from f0, frame f1 holds the others' f1 images (lent f0's poses)
    and rig03's f0 image (the run's own): the terminal called f1 'a frame of the run without some of their narrow
    images', a frame the run was not given. Only a view of the frame itself (its own file name) makes it the run's."""
    from rigsfm.cli.associate import lent_lines, written_frames

    lent = ["rig01/narrow/f1.png", "rig02/narrow/f1.png"]
    data = {"frame": "f1.png", "views": [*lent, "rig03/narrow/f0.png"], "poses_from": "f0.png", "lent_views": lent,
            "persons": [], "unassigned": []}
    (tmp_path / "f1").mkdir()
    (tmp_path / "f1" / "persons.json").write_text(json.dumps(data))
    assert lent_lines(written_frames(tmp_path), "f0.png", Path("out")) == [
        "1 frame(s) the run was not given: associated with the narrow poses of its frame f0.png (static rigs; "
        "`rigsfm track out IMAGES` tells whether a rig moved)"]


def test_the_report_says_the_density_grid_counts_the_persons_found(tmp_path):
    """The density grid counts the persons the association found (detected in two views or more): on a rendered
    8-rig crowd 0.40-0.42x the true heads in its cells (benchmarks/README.md). report.html captioned it 'persons per
    m2', which a crowd researcher reads as the crowd's density."""
    from rigsfm.associate.report import associate_report_section

    folder = Workspace(tmp_path).associate / "f0"
    folder.mkdir(parents=True)
    (folder / "persons.json").write_text(json.dumps({"frame": "f0.png", "views": [], "persons": [],
                                                     "unassigned": []}))
    (folder / "density.png").write_bytes(b"\x89PNG")
    section = associate_report_section(tmp_path)
    assert "persons found per m2" in section and "a fraction of those there" in section



def test_a_recording_the_offsets_check_could_not_test_is_said(tmp_path):
    """A recording of five frames with one rig's narrow image missing in its middle frame: no frame has every view in
    the frames around it, so the check of the rigs' timing tested nothing, and the terminal said nothing, though the
    docs promise a recording of three frames or more is checked (a rig one frame late went unnamed). A recording of
    a frame or two is still not spoken of."""
    from rigsfm.associate.output import MANIFEST
    from rigsfm.associate.sync import SyncCheck
    from rigsfm.cli.associate import offsets_line

    check = SyncCheck("check", skipped="no frame with every narrow view in the frames around it")
    (tmp_path / MANIFEST).write_text(json.dumps({"frame_offsets": check.to_dict()}))
    assert offsets_line(tmp_path) == ("frame offsets (check): not checked (no frame with every narrow view in the "
                                      "frames around it): whether the rigs took their frames together is unknown")
    not_a_recording = SyncCheck("check", skipped="three frames and three narrow views are needed")
    (tmp_path / MANIFEST).write_text(json.dumps({"frame_offsets": not_a_recording.to_dict()}))
    assert offsets_line(tmp_path) is None


def test_an_image_changed_since_the_run_is_named_once_per_command(tmp_path, caplog):
    """An image changed since the run was named once per association of its frame: three times in one command with
    --frame-offsets auto (the frame, the timing check, the frames paired again), twice with the default check."""
    import dataclasses as dc

    from rigsfm.associate.pipeline import RunModel, _run_image_grey
    from rigsfm.core.io import file_sha256

    image = tmp_path / "rig01" / "narrow" / "f0.png"
    image.parent.mkdir(parents=True)
    image.write_bytes(b"the image the run read")
    recorded = file_sha256(image)
    image.write_bytes(b"another recording under the same name")
    model = RunModel({}, {}, set(), None, images_root=tmp_path, image_sha256={"rig01/narrow/f0.png": recorded})
    with caplog.at_level("WARNING"):
        for same_command in (model, dc.replace(model, bands={("a", "b"): 1.0})):  # the command's models, replaced
            assert _run_image_grey(same_command, "rig01/narrow/f0.png") is None
            assert _run_image_grey(same_command, "rig01/narrow/f0.png") is None
    assert sum("changed since the run" in r.getMessage() for r in caplog.records) == 1
