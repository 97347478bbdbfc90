"""Inputs that used to run to the end silently wrong, or fail after the heavy work with a misleading message, are
refused at validation with one line naming the file, the rig or entry, the key and the fix."""

import copy
import json
import logging
import math
import os

import numpy as np
import pytest
import yaml
from test_bad_input import H, W, expect, write_rigs
from test_bad_input import make_inputs as make_aliased_inputs

from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.rig import RigSigmas, load_rigs
from rigsfm.core.rig import write_rigs as write_rig_file
from rigsfm.core.workspace import Workspace, read_json, read_model
from rigsfm.run.matching.manual_matches import ManualMatchError, read_manual_matches
from rigsfm.run.options import AdjustOptions, MappingOptions, MatchingOptions, RunOptions
from rigsfm.run.pipeline import load_inputs

SIGMAS = {"wide": [0.4, 0.4, 0.5, 0.5], "narrow": [1.5, 1.5, 0.8, 0.9]}
POSE_SIGMAS = {"sigma_rotation_deg": [0.02, 0.03, 0.01], "sigma_translation_m": [1e-4, 1e-4, 3e-4]}


def make_inputs(root):
    """test_bad_input's inputs with every camera a dict of its own (there, wide and narrow share one)."""
    images, rigs_path, data = make_aliased_inputs(root)
    data = json.loads(json.dumps(data))
    write_rigs(rigs_path, data)
    return images, rigs_path, data


def with_sigmas(data):
    data = copy.deepcopy(data)
    for rig in data["rigs"]:
        for sensor, values in SIGMAS.items():
            rig["sensors"][sensor]["sigmas"] = list(values)
        rig["narrow_from_wide"].update(copy.deepcopy(POSE_SIGMAS))
    return data


# --- rigs.yaml: units, principal point, focal length, unknown keys -------------------------------------------

@pytest.mark.parametrize("translation,words", [
    ([-60.0, 0.0, 0.0], r"rig 'rig02' narrow_from_wide translation: the baseline \|t\| = 60 m is outside 1 mm - 5 m "
                        r"\(in millimetres\? 60 mm is 0.06 m\); give the translation in metres"),
    ([0.0, 0.0, 0.0], r"rig 'rig02' narrow_from_wide translation: the baseline \|t\| = 0 m .*cannot be at one point"),
    ([0.0004, 0.0, 0.0], r"rig 'rig02' narrow_from_wide translation: .*0.0004 m is outside"),
])
def test_baseline_in_other_units_than_metres_is_refused(tmp_path, translation, words):
    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][1]["narrow_from_wide"]["translation"] = translation
    write_rigs(rigs_path, data)
    expect(tmp_path, words, images, rigs_path)


def test_baselines_at_the_limits_are_accepted(tmp_path):
    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][0]["narrow_from_wide"]["translation"] = [0.0011, 0.0, 0.0]
    data["rigs"][1]["narrow_from_wide"]["translation"] = [0.0, 4.9, 0.0]
    write_rigs(rigs_path, data)
    assert len(load_inputs(images, rigs_path).rigs) == 2


@pytest.mark.parametrize("params,words", [
    ([50.0, 50.0, 64.5, 24.0], r"rig 'rig01' sensor narrow: principal point \(64.5, 24\) lies outside the 64x48 image"),
    ([50.0, 50.0, 32.0, -1.0], r"principal point \(32, -1\) lies outside"),
    ([4.0, 4.0, 32.0, 24.0], r"rig 'rig01' sensor narrow: focal length fx = 4 px is 0.0625 x the image width 64; a lens "
                             r"has 0.1-50 x .* not millimetres"),
    ([50.0, 5000.0, 32.0, 24.0], r"focal length fy = 5000 px is 78.1 x"),
    ([50.0, 180.0, 32.0, 24.0], r"fx / fy = 0.278; .*check the params' order"),
])
def test_implausible_intrinsics_are_refused(tmp_path, params, words):
    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][0]["sensors"]["narrow"]["params"] = params
    write_rigs(rigs_path, data)
    expect(tmp_path, words, images, rigs_path)


@pytest.mark.parametrize("focal_widths", [0.2, 3.0, 10.0, 40.0])
def test_fisheye_and_long_lenses_are_plausible(tmp_path, focal_widths):
    images, rigs_path, data = make_inputs(tmp_path)
    f = focal_widths * W
    data["rigs"][0]["sensors"]["narrow"] = {"model": "OPENCV_FISHEYE", "width": W, "height": H,
                                            "params": [f, f, W / 2, H / 2, 0.01, 0.0, 0.0, 0.0]}
    write_rigs(rigs_path, data)
    assert load_inputs(images, rigs_path).rigs[0].narrow.focal_length_x == pytest.approx(f)


@pytest.mark.parametrize("where,key,words", [
    ("top", "unit", r"rigs.yaml: unknown key 'unit' \(did you mean 'units'\?\); the keys here are units, rigs"),
    ("rig", "narow_from_wide", r"rig 'rig02': unknown key 'narow_from_wide' \(did you mean 'narrow_from_wide'\?\)"),
    ("camera", "param", r"rig 'rig02' sensor wide: unknown key 'param' \(did you mean 'params'\?\)"),
    ("pose", "tranlsation", r"rig 'rig02' narrow_from_wide: unknown key 'tranlsation' \(did you mean 'translation'\?\)"),
    ("pose", "sigma_rotation", r"unknown key 'sigma_rotation' \(did you mean 'sigma_rotation_deg'\?\)"),
    ("sensors", "wide2", r"rig 'rig02' sensors: unknown key 'wide2' \(did you mean 'wide'\?\)"),
    ("camera", "comment", r"unknown key 'comment'; the keys here are model, width, height, params, sigmas"),
])
def test_unknown_keys_are_refused_with_a_suggestion(tmp_path, where, key, words):
    images, rigs_path, data = make_inputs(tmp_path)
    rig = data["rigs"][1]
    target = {"top": data, "rig": rig, "camera": rig["sensors"]["wide"], "pose": rig["narrow_from_wide"],
              "sensors": rig["sensors"]}[where]
    target[key] = 1
    write_rigs(rigs_path, data)
    expect(tmp_path, words, images, rigs_path)


def test_equirectangular_has_no_focal_length_and_is_refused(tmp_path):
    """pycolmap segfaults on the focal length of an EQUIRECTANGULAR camera: it must never get that far."""
    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][0]["sensors"]["wide"] = {"model": "EQUIRECTANGULAR", "width": W, "height": H, "params": [W, H]}
    write_rigs(rigs_path, data)
    expect(tmp_path, r"unknown camera model 'EQUIRECTANGULAR'", images, rigs_path)


def test_missing_narrow_folder_is_a_warning_not_an_error(tmp_path, caplog):
    images, rigs_path, _ = make_inputs(tmp_path)
    for path in (images / "rig02" / "narrow").iterdir():
        path.unlink()
    (images / "rig02" / "narrow").rmdir()
    with caplog.at_level(logging.WARNING):
        inputs = load_inputs(images, rigs_path)
    assert [e.name for e in inputs.images if e.rig == "rig02"] == ["rig02/wide/f0.png"]
    assert any(f"rig 'rig02' has no narrow images ('{images / 'rig02' / 'narrow'}' does not exist)" in r.message
               for r in caplog.records), caplog.text


def test_a_frame_without_its_narrow_image_is_a_warning(tmp_path, caplog):
    """A narrow file forgotten in one frame: the run goes on (that frame's narrow camera gets no pose) and says so;
    it finished without a word."""
    import shutil

    images, rigs_path, _ = make_inputs(tmp_path)
    shutil.copy(images / "rig01" / "wide" / "f0.png", images / "rig01" / "wide" / "f1.png")
    with caplog.at_level(logging.WARNING):
        inputs = load_inputs(images, rigs_path)
    assert "rig01/wide/f1.png" in [e.name for e in inputs.images]
    assert inputs.without_narrow == ("rig 'rig01' has none in 1 of its 2 frames ('f1.png'): its narrow camera gets "
                                     "no pose in them",), inputs.without_narrow
    assert "NO NARROW IMAGES: rig 'rig01' has none in 1 of its 2 frames" in caplog.text


def test_a_rig_lacking_whole_frames_is_one_warning_naming_the_rigs_and_frames(tmp_path, caplog):
    """rig02 lacks f2 and rig03 lacks f1 and f2 (wide and narrow), which rig01 has: the run went on without a word.
    One warning names each rig and its frames; the inputs keep it for summary.json."""
    import shutil

    images, rigs_path, data = make_inputs(tmp_path)
    shutil.copytree(images / "rig02", images / "rig03")
    data["rigs"].append(dict(copy.deepcopy(data["rigs"][1]), name="rig03"))
    write_rigs(rigs_path, data)
    for frame in ("f1.png", "f2.png"):
        for rig in ("rig01", "rig02") if frame == "f1.png" else ("rig01",):
            for sensor in ("wide", "narrow"):
                shutil.copy(images / rig / sensor / "f0.png", images / rig / sensor / frame)
    with caplog.at_level(logging.WARNING):
        inputs = load_inputs(images, rigs_path)
    assert inputs.missing_frames == (
        "1 of 3 rigs lack frames other rigs have ('rig03' lacks 'f1.png'; 'f2.png' is only in 'rig01'; 3 frames in "
        "all): a rig adds no view at a frame it lacks; check for a file misnamed or not copied"), inputs.missing_frames
    assert [r.message for r in caplog.records].count(f"MISSING FRAMES: {inputs.missing_frames}") == 1, caplog.text
    # one rig's misnamed frame: that rig is named, not the others for lacking its odd name
    for sensor in ("wide", "narrow"):
        (images / "rig03" / sensor / "f0.png").rename(images / "rig03" / sensor / "f_0.png")
    assert load_inputs(images, rigs_path).missing_frames == (
        "1 of 3 rigs lack frames other rigs have ('rig03' lacks 'f0.png', 'f1.png'; 'f2.png' is only in 'rig01'; "
        "'f_0.png' is only in 'rig03'; 4 frames in all): a rig adds no view at a frame it lacks; check for a file "
        "misnamed or not copied")
    assert load_inputs(*make_inputs(tmp_path / "whole")[:2]).missing_frames is None


# --- rigs.yaml: the calibration uncertainties ---------------------------------------------------------------

def test_sigmas_are_read_onto_the_rig_calibration_and_written_back(tmp_path):
    images, rigs_path, data = make_inputs(tmp_path)
    write_rigs(rigs_path, with_sigmas(data))
    rigs = load_inputs(images, rigs_path).rigs
    sigmas = rigs[1].sigmas
    assert isinstance(sigmas, RigSigmas)
    np.testing.assert_allclose(sigmas.wide, SIGMAS["wide"])
    np.testing.assert_allclose(sigmas.narrow, SIGMAS["narrow"])
    np.testing.assert_allclose(sigmas.rotation_deg, POSE_SIGMAS["sigma_rotation_deg"])
    np.testing.assert_allclose(sigmas.translation_m, POSE_SIGMAS["sigma_translation_m"])
    assert sigmas.covariance is None
    again = tmp_path / "again.yaml"
    write_rig_file(again, rigs)
    back = load_rigs(again)
    np.testing.assert_allclose(back[1].sigmas.narrow, SIGMAS["narrow"])
    np.testing.assert_allclose(back[0].sigmas.translation_m, POSE_SIGMAS["sigma_translation_m"])


def test_a_rigs_yaml_without_sigmas_stays_valid(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    assert all(rig.sigmas is None for rig in load_inputs(images, rigs_path).rigs)


@pytest.mark.parametrize("edit,words", [
    (lambda r: r["sensors"]["wide"].update(sigmas=[-0.4, 0.4, 0.5, 0.5]),
     r"rig 'rig02' sensor wide sigmas \(one per entry of params\): expected 4 finite numbers >= 0"),
    (lambda r: r["sensors"]["wide"].update(sigmas=[0.4, float("nan"), 0.5, 0.5]), r"sensor wide sigmas .*finite"),
    (lambda r: r["sensors"]["narrow"].update(sigmas=[0.0, 0.4, 0.5, 0.5]),
     r"rig 'rig02' sensor narrow sigmas .*\(fx\): the focal length's sigma 0 px must be at least 0.0001 px .*"
     r"and at most 10 % of 50 px"),
    (lambda r: r["sensors"]["narrow"].update(sigmas=[6.0, 0.4, 0.5, 0.5]),
     r"the focal length's sigma 6 px must be at least 0.0001 px .*and at most 10 %"),
    (lambda r: r["sensors"]["wide"].update(sigmas=[0.4, 0.4, 9.0, 0.5]), r"the principal point's sigma 9 px"),
    (lambda r: r["narrow_from_wide"].update(sigma_rotation_deg=[0.02, 6.0, 0.01]),
     r"rig 'rig02' narrow_from_wide sigma_rotation_deg: each must be 1e-06 - 5 degrees"),
    (lambda r: r["narrow_from_wide"].update(sigma_rotation_deg=[0.02, 0.0, 0.01]), r"sigma_rotation_deg: each must be 1e-06 - 5 degrees"),
    (lambda r: r["narrow_from_wide"].update(sigma_translation_m=[0.1, 0.0, 0.0]),
     r"rig 'rig02' narrow_from_wide sigma_translation_m: each must be at least 1e-07 m and below the baseline "
     r"\|t\| = 0.06 m"),
    (lambda r: r["narrow_from_wide"].update(covariance=(np.eye(6) * 0.01).tolist()),
     r"rig 'rig02' narrow_from_wide covariance: a rotation variance above \(5 deg\)\^2"),
    (lambda r: r["narrow_from_wide"].update(covariance=[[1.0]]), r"covariance: expected a finite 6x6 matrix"),
])
def test_bad_sigmas_are_refused_naming_rig_and_key(tmp_path, edit, words):
    images, rigs_path, data = make_inputs(tmp_path)
    data = with_sigmas(data)
    edit(data["rigs"][1])
    write_rigs(rigs_path, data)
    expect(tmp_path, words, images, rigs_path)


def test_distortion_sigmas_may_be_zero_held_fixed(tmp_path):
    images, rigs_path, data = make_inputs(tmp_path)
    camera = {"model": "OPENCV", "width": W, "height": H, "params": [50.0, 50.0, 32.0, 24.0, 0.01, 0.0, 0.0, 0.0],
              "sigmas": [0.4, 0.4, 0.5, 0.5, 1e-3, 0.0, 0.0, 0.0]}
    data["rigs"][0]["sensors"]["wide"] = camera
    write_rigs(rigs_path, data)
    assert load_inputs(images, rigs_path).rigs[0].sigmas.wide[5] == 0.0


# --- scale.yaml ------------------------------------------------------------------------------------------------

def scale_file(tmp_path, data):
    path = tmp_path / "scale.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def bar(a0=(10, 10), b0=(20, 12), a1=(30, 20), b1=(40, 22), image1="rig02/wide/f0.png"):
    return {"known_length": [{"meters": 2.0, "observations": [
        {"image": "rig01/wide/f0.png", "a": list(a0), "b": list(b0)},
        {"image": image1, "a": list(a1), "b": list(b1)}]}]}


def test_valid_bar_loads(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    assert load_inputs(images, rigs_path, scale_file(tmp_path, bar())).scale.known_lengths[0].meters == 2.0


@pytest.mark.parametrize("data,words", [
    (bar(b1=(40, H + 3)), r"known_length\[0\].observations\[1\].b: \(40, 51\) lies outside 'rig02/wide/f0.png', "
                          r"which is 64x48 px .*fix the coordinates"),
    (bar(a0=(-2, 10)), r"known_length\[0\].observations\[0\].a: \(-2, 10\) lies outside 'rig01/wide/f0.png'"),
    (bar(image1="rig02/narrow/f0.png", a1=(70, 5)), r"observations\[1\].a: \(70, 5\) lies outside 'rig02/narrow/f0.png'"),
    (bar(a1=(30, 20), b1=(30.4, 20.2)), r"known_length\[0\].observations\[1\]: a and b are the same point in "
                                        r"'rig02/wide/f0.png' \(a zero-length bar\)"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig01/wide/f0.png", "meters": 3}]},
     r"camera_distance\[0\]: a = 'rig01/wide' and b = 'rig01/wide/f0.png' are the same camera \(zero distance\)"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 3, "sigm": 0.1}]},
     r"camera_distance\[0\]: unknown key 'sigm' \(did you mean 'sigma'\?\)"),
    ({"camera_distances": []}, r"scale.yaml: unknown key 'camera_distances' \(did you mean 'camera_distance'\?\)"),
    ({"known_length": {"meters": 2}}, r"known_length must be a list of entries"),
    ({"camera_distance": [{"a": ["rig01/wide"], "b": "rig02/wide", "meters": 3}]}, r"a = \['rig01/wide'\] names no camera"),
    ({"pixel_sigma": 10**400, "camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 3}]},
     r"pixel_sigma must be a number"),
])
def test_bad_scale_entries_are_refused_at_validation(tmp_path, data, words):
    images, rigs_path, _ = make_inputs(tmp_path)
    expect(tmp_path, words, images, rigs_path, scale_file(tmp_path, data))


# --- options -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("value", [0, 0.0, -0.5, 1.0001, 2, math.nan, math.inf, "0.8", True, None])
def test_max_ratio_outside_0_1_is_refused(value):
    with pytest.raises(InputError, match=r"--max-ratio \(Lowe's ratio test\) must be a number > 0 and <= 1"):
        MatchingOptions(max_ratio=value)


@pytest.mark.parametrize("make,words", [
    (lambda: MatchingOptions(max_error_px=0), r"max_error_px must be a number > 0"),
    (lambda: MatchingOptions(max_num_features=0), r"max_num_features must be an integer >= 1"),
    (lambda: MatchingOptions(features="surf"), r"--features must be one of sift, asift, got 'surf'"),
    (lambda: MappingOptions(mapper="glomap"), r"--mapper must be one of auto, incremental, global"),
    (lambda: MappingOptions(seed=-2), r"--seed \(-1: random\) must be an integer >= -1"),
    (lambda: AdjustOptions(loss_scale_px=math.nan), r"loss_scale_px must be a number > 0"),
    (lambda: AdjustOptions(max_iterations=0), r"max_iterations must be an integer >= 1"),
    (lambda: RunOptions(num_threads=0), r"num_threads \(-1: all cores\) must be an integer >= 1"),
])
def test_other_bad_options_are_refused(make, words):
    with pytest.raises(InputError, match=words):
        make()


def test_good_options_are_kept():
    assert MatchingOptions(max_ratio=1).max_ratio == 1
    assert MatchingOptions(features="asift").features == "asift"
    assert MappingOptions(seed=np.int64(3), mapper="global").mapper == "global"


# --- matches.csv from a spreadsheet ---------------------------------------------------------------------------------

CSV = "image_a,x_a,y_a,image_b,x_b,y_b\nrig01/wide/f0.png,1.5,2,rig02/wide/f0.png,3,4.25\n"


@pytest.mark.parametrize("encoding", ["utf-8", "utf-8-sig", "utf-16", "utf-16-be"])
def test_matches_csv_with_a_byte_order_mark_is_read(tmp_path, encoding):
    path = tmp_path / "m.csv"
    data = CSV.encode(encoding)
    if encoding == "utf-16-be":
        data = b"\xfe\xff" + data
    path.write_bytes(data)
    (row,) = read_manual_matches(path)
    assert (row.image_a, row.xy_a, row.image_b, row.xy_b, row.line) == \
        ("rig01/wide/f0.png", (1.5, 2.0), "rig02/wide/f0.png", (3.0, 4.25), 2)


@pytest.mark.parametrize("data,words", [
    (CSV.encode("utf-16-le"), r"m.csv: holds NUL characters .*save it as CSV UTF-8"),
    (CSV.replace("f0", "fé").encode("latin-1"), r"m.csv: not UTF-8 text \(byte \d+\); save it as UTF-8"),
    (CSV.replace(",", ";").encode(), r"m.csv:1: the columns are separated by semicolons; save it as comma-separated"),
])
def test_matches_csv_in_other_encodings_is_refused_clearly(tmp_path, data, words):
    path = tmp_path / "m.csv"
    path.write_bytes(data)
    with pytest.raises(ManualMatchError, match=words):
        read_manual_matches(path)


def test_rigs_yaml_with_a_byte_order_mark_is_read(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    rigs_path.write_bytes(rigs_path.read_text().encode("utf-8-sig"))
    assert len(load_inputs(images, rigs_path).rigs) == 2


# --- damaged workspace files ------------------------------------------------------------------------------------------

def test_a_damaged_model_names_the_folder_and_the_fix(tmp_path):
    import pycolmap

    from rigsfm.core.rig import RigCalibration, add_posed_rig

    rig = load_inputs(*make_inputs(tmp_path)[:2]).rigs[0]
    model = pycolmap.Reconstruction()
    add_posed_rig(model, 1, RigCalibration(rig.name, rig.wide, rig.narrow, rig.narrow_from_wide), pycolmap.Rigid3d(),
                  [{"wide": "rig01/wide/f0.png", "narrow": "rig01/narrow/f0.png"}])
    sparse = tmp_path / "out" / "sparse"
    sparse.mkdir(parents=True)
    model.write(sparse)
    assert read_model(sparse, "fix it").num_images() == 2
    images = (sparse / "images.bin").read_bytes()
    (sparse / "images.bin").write_bytes(images[:20])
    with pytest.raises(WorkspaceError, match=r"sparse/images.bin' is truncated or damaged \(20 B; says 2 images but "
                                             r"only 12 B follow\): re-run `rigsfm run IMAGES"):
        Workspace(tmp_path / "out").read_sparse()
    (sparse / "images.bin").unlink()
    with pytest.raises(WorkspaceError, match=r"sparse' holds no complete COLMAP model \(images.bin missing\): fix"):
        read_model(sparse, "fix")


@pytest.mark.parametrize("text,words", [
    ('{"narrow": [], "pairs": [', r"narrow_poses.json' is not valid JSON \(.*\): re-run `rigsfm run"),
    ("[]", r"narrow_poses.json' is not a file rigsfm wrote \(no narrow, pairs\)"),
    ("\udcff", r"narrow_poses.json' is not valid JSON"),
])
def test_a_damaged_json_file_names_itself(tmp_path, text, words):
    workspace = Workspace(tmp_path)
    workspace.narrow_poses.write_bytes(text.encode("utf-8", "surrogateescape"))
    with pytest.raises(WorkspaceError, match=words):
        workspace.read_narrow_poses()
    with pytest.raises(WorkspaceError, match=r"nothing.json' is missing: fix"):
        read_json(tmp_path / "nothing.json", "fix")


# --- plausibility, not only syntax: keys given twice, Unicode names, what is not a regular file ----------------

def _set_text(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize("edit,words", [
    (lambda text: text.replace("    wide:", "    wide:\n      model: PINHOLE\n    wide:", 1),
     r"rigs.yaml line \d+, column 5: the key 'wide' is given twice \(first on line \d+\)"),
    (lambda text: "units: meters\n" + text, r"rigs.yaml line \d+, column 1: the key 'units' is given twice "
                                            r"\(first on line 1\)"),
])
def test_a_key_given_twice_is_refused_naming_key_and_lines(tmp_path, edit, words):
    images, rigs_path, _ = make_inputs(tmp_path)
    rigs_path.write_text(edit(rigs_path.read_text()))
    expect(tmp_path, words, images, rigs_path)


def test_a_key_given_twice_in_scale_yaml_or_json_is_refused(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    scale = tmp_path / "scale.yaml"
    scale.write_text("camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 3}]\n"
                     "camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 30}]\n")
    expect(tmp_path, r"scale.yaml line 2, column 1: the key 'camera_distance' is given twice \(first on line 1\)",
           images, rigs_path, scale)
    scale.write_text('{"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 3, "meters": 4}]}')
    expect(tmp_path, r"scale.yaml line 1, column \d+: the key 'meters' is given twice", images, rigs_path, scale)


def test_yaml_merge_keys_may_still_override(tmp_path):
    from rigsfm.core.io import parse_yaml

    assert parse_yaml("x: &a {k: 1, j: 2}\ny:\n  <<: *a\n  k: 3\n") == {"x": {"k": 1, "j": 2}, "y": {"k": 3, "j": 2}}


@pytest.mark.parametrize("text", [
    "a: 010", "a: -010", "a: 0o17", "a: 0x1F", "a: 0b101", "a: 1_000", "a: 1:30", "a: -0", "a: +12", "a: 0",
    "a: 1.5", "a: 1_0.5", "a: 1:30.5", "a: .inf", "a: -.Inf", "a: .5", "a: 1.", "a: 1e5", "a: 1.0e+5",
    "a: yes", "a: Off", "a: ~", "a: null", "a: ''", "a: '1.5'", "a: !!float 3", "a: !!int '7'",
    "a: 2001-12-14", "a: !!binary aGk=", "? [1, 2]\n: 3", "'1': 2\n1: 3", "[1, 2, {a: b}]", "", "1",
    "a: &x [1, {k: v}]\nb: *x", "a: &x [1, *x]", "x: &a {k: 1}\ny: {<<: *a, j: 2}",
])
def test_the_fast_yaml_reader_reads_what_pyyaml_reads(text):
    """parse_yaml builds plain documents itself (PyYAML's constructor is the slow half of a large rigs.yaml):
    every scalar form, anchors, merge keys and cyclic documents read as yaml.safe_load reads them."""
    from rigsfm.core.io import parse_yaml

    def outcome(load):
        try:
            return repr(load(text))
        except yaml.YAMLError as error:
            return type(error).__name__

    assert outcome(parse_yaml) == outcome(yaml.safe_load)
    shared = parse_yaml("a: &x [1, {k: v}]\nb: *x")
    assert shared["a"] is shared["b"]  # an anchored node is one object, as PyYAML makes it


def test_a_key_given_twice_is_refused_at_any_depth_outermost_first():
    from rigsfm.core.io import DuplicateKeyError, parse_yaml

    with pytest.raises(DuplicateKeyError, match=r"the key 'a' is given twice \(first on line 1\)"):
        parse_yaml("a: {x: 1, x: 2}\nb: 0\na: 3\n")
    with pytest.raises(DuplicateKeyError, match=r"the key 'x' is given twice \(first on line 2\)") as error:
        parse_yaml("rigs:\n  - {x: 1,\n     y: 2, x: 3}\n")
    assert error.value.problem_mark.line == 2


@pytest.mark.parametrize("edit,words", [
    (lambda p: _set_text(p, "name: rig01", "name: 1"),
     r"rigs\[0\]: rig name 1 is read as a number, not text; quote it \(name: \"1\"\)"),
    (lambda p: p.write_text(p.read_text() + "scale: 1,5\n"), r"unknown key 'scale'"),
    (lambda p: p.write_text("units: meters\nrigs: [{name: rig01, sensors: 12,5}]\n"),
     r"rigs.yaml: rig 'rig01': unknown key 5 with no value: a decimal comma\? Inside \{...\} or \[...\], a comma "
     r"separates values \('25,5' is 25 and 5\); write decimals with a point \(25.5\)"),
    (lambda p: p.write_text("rigs:\n  - name: rig01\n\tsensors: {}\n"),
     r"rigs.yaml line 3, column 1: not valid YAML/JSON \(found a tab character that violates indentation while "
     r"scanning a plain scalar\); fix the syntax"),
    # beyond Python's 4300-digit limit on converting text to int, which PyYAML's int() raised as a traceback
    (lambda p: _set_text(p, "width: 64", "width: " + "9" * 5000),
     r"rigs.yaml line \d+, column \d+: a whole number of 5000 digits is beyond any value here; give the number"),
])
def test_yaml_mistakes_say_their_line_and_cause(tmp_path, edit, words):
    images, rigs_path, _ = make_inputs(tmp_path)
    edit(rigs_path)
    expect(tmp_path, words, images, rigs_path)


def test_decimal_comma_in_scale_yaml_is_named(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    scale = tmp_path / "scale.yaml"
    scale.write_text("camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 25,981073133815897}]\n")
    expect(tmp_path, r"camera_distance\[0\]: unknown key 981073133815897 with no value: a decimal comma\?", images,
           rigs_path, scale)


def _nfd_inputs(tmp_path):
    import unicodedata

    images, rigs_path, data = make_inputs(tmp_path)
    composed, decomposed = unicodedata.normalize("NFC", "rigé"), unicodedata.normalize("NFD", "rigé")
    assert composed != decomposed
    (images / "rig01").rename(images / decomposed)
    data["rigs"][0]["name"] = composed
    rigs_path.write_text(yaml.safe_dump(data, allow_unicode=True))
    return images, rigs_path, composed, decomposed


def test_a_decomposed_rig_folder_matches_its_composed_name(tmp_path):
    images, rigs_path, composed, decomposed = _nfd_inputs(tmp_path)
    scale = scale_file(tmp_path, {"camera_distance": [{"a": f"{composed}/wide", "b": "rig02/wide", "meters": 3.0}],
                                  "known_length": bar()["known_length"]})
    scale.write_text(scale.read_text().replace("rig01", composed))
    inputs = load_inputs(images, rigs_path, scale)
    assert inputs.rigs[0].name == decomposed  # the folder's spelling: every image name reads its file
    assert all(e.path.is_file() and (images / e.name).is_file() for e in inputs.images)
    assert inputs.scale.camera_distances[0].a == f"{decomposed}/wide"
    assert inputs.scale.known_lengths[0].observations[0].image == f"{decomposed}/wide/f0.png"
    assert inputs.priors is not None


def test_one_rig_folder_in_two_unicode_spellings_is_refused(tmp_path):
    images, rigs_path, composed, decomposed = _nfd_inputs(tmp_path)
    (images / composed / "wide").mkdir(parents=True)
    expect(tmp_path, r"folders .* are the same name in two Unicode spellings", images, rigs_path)


def test_rig_names_equal_in_nfc_are_duplicates(tmp_path):
    import unicodedata

    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][0]["name"] = unicodedata.normalize("NFC", "rigé")
    data["rigs"][1]["name"] = unicodedata.normalize("NFD", "rigé")
    rigs_path.write_text(yaml.safe_dump(data, allow_unicode=True))
    with pytest.raises(InputError, match=r"rig names must be unique, repeated: .* \(rigs\[0\] and rigs\[1\]\)"):
        load_rigs(rigs_path)


def _socket(path):
    import socket

    server = socket.socket(socket.AF_UNIX)
    server.bind(str(path))
    return server


@pytest.mark.parametrize("make,words", [
    (lambda p: os.mkfifo(p), r"f1.png' is a FIFO \(named pipe\), not an image file; replace it"),
    (lambda p: os.symlink("/dev/null", p), r"f1.png' is a character device, not an image file"),
    (_socket, r"f1.png' is a socket, not an image file"),
    (lambda p: os.symlink(p.name, p), r"f1.png' is a symbolic link loop"),
    (lambda p: os.symlink("missing.png", p), r"f1.png' is a symbolic link to missing.png, which does not exist"),
    (lambda p: p.mkdir(), r"f1.png: sub-folders are not allowed"),
])
def test_what_is_not_a_regular_image_file_is_refused_before_any_read(tmp_path, make, words):
    from rigsfm.core.rig import load_rigs as read_rigs
    from rigsfm.run.inputs.images import scan_images

    images, rigs_path, _ = make_inputs(tmp_path)
    keep = make(images / "rig02" / "wide" / "f1.png")
    # check_pixels=False is rigsfm track's scan: no image is read, so a FIFO is refused here or never
    with pytest.raises(InputError, match=words):
        scan_images(images, read_rigs(rigs_path), check_pixels=False)
    if keep is not None:
        keep.close()


@pytest.mark.parametrize("make,words", [
    (lambda p: p.mkdir(), r"rig calibration file '\S+' is a folder, not a regular file; give the path of the rig "
                          r"calibration file itself"),
    (lambda p: os.mkfifo(p), r"is a FIFO \(named pipe\), not a regular file"),
    (lambda p: os.symlink("/dev/zero", p), r"is a character device, not a regular file"),
    (lambda p: os.symlink(p.name, p), r"is a symbolic link loop \(it points, through links, back at itself\)"),
    (lambda p: os.symlink("gone.yaml", p), r"is a symbolic link to gone.yaml, which does not exist"),
])
def test_an_input_file_that_exists_but_is_no_file_gets_its_true_cause(tmp_path, make, words):
    target = tmp_path / "given.yaml"
    make(target)
    with pytest.raises(InputError, match=words):
        load_rigs(target)


def test_an_image_folder_that_is_a_file_is_named_as_such(tmp_path):
    images, rigs_path, _ = make_inputs(tmp_path)
    with pytest.raises(InputError, match=r"image folder '\S+rigs.yaml' is a file, not a folder"):
        load_inputs(rigs_path, rigs_path)


def _as_nobody(code: str, root) -> str:
    """Run ``code`` as user nobody (root reads everything); the error line it prints."""
    import shutil
    import subprocess
    import sys

    if os.geteuid() != 0:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root).stdout
    if shutil.which("setpriv") is None:
        pytest.skip("needs setpriv to drop root")
    env = dict(os.environ, PYTHONPATH=os.environ.get("PYTHONPATH", ""))
    return subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c", code],
                          capture_output=True, text=True, cwd=root, env=env).stdout


@pytest.fixture
def shared_tmp():
    import shutil
    import tempfile
    from pathlib import Path

    root = Path(tempfile.mkdtemp(prefix="rigsfm-perm-"))
    root.chmod(0o755)
    yield root
    for path in root.rglob("*"):
        if path.is_dir() and not path.is_symlink():
            path.chmod(0o755)
    shutil.rmtree(root)


PROBE = """
from rigsfm.core.errors import RigsfmError
from rigsfm.run.pipeline import load_inputs
try:
    load_inputs('images', 'rigs.yaml')
except RigsfmError as error:
    print(error)
"""


@pytest.mark.parametrize("deny,words", [
    (lambda root: (root / "rigs.yaml").chmod(0), r"rig calibration file 'rigs.yaml' cannot be read: permission denied"),
    (lambda root: (root / "images" / "rig01" / "wide").chmod(0), r"folder 'images/rig01/wide' cannot be read: "
                                                                 r"permission denied .*give yourself read permission"),
    (lambda root: (root / "images" / "rig02" / "wide" / "f0.png").chmod(0),
     r"images/rig02/wide/f0.png' cannot be read: permission denied"),
])
def test_a_permission_denial_is_called_so(shared_tmp, deny, words):
    import re

    make_inputs(shared_tmp)
    for path in shared_tmp.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    deny(shared_tmp)
    line = _as_nobody(PROBE, shared_tmp)
    assert re.search(words, line), line
    assert "corrupt" not in line and "write to" not in line


@pytest.mark.parametrize("edit,words", [
    (lambda c: c.update(width=int("9" * 300)), r"width must be a whole number of pixels, 1 to 100000, got a "
                                               r"300-digit number"),
    (lambda c: c.update(width=64.5), r"width must be a whole number of pixels"),
    (lambda c: c.update(height=True), r"height must be a whole number of pixels"),
    (lambda c: c.update(model="EUCM", params=[50.0, 50.0, 32.0, 24.0, 7.0, 1.0]),
     r"EUCM's alpha = 7 lies outside its domain 0 - 1"),
    (lambda c: c.update(model="EUCM", params=[50.0, 50.0, 32.0, 24.0, 0.5, -1.0]), r"EUCM's beta = -1 lies outside"),
    (lambda c: c.update(model="FOV", params=[50.0, 50.0, 32.0, 24.0, -0.9]), r"FOV's omega = -0.9 lies outside"),
    (lambda c: c.update(model="OPENCV", params=[50.0, 50.0, 32.0, 24.0, 1e6, 0.0, 0.0, 0.0]),
     r"distortion coefficient k1 = 1e\+06 is beyond any lens"),
    (lambda c: c.update(model="OPENCV", params=[50.0, 50.0, 32.0, 24.0, 900.0, 0.0, 0.0, 0.0]),
     r"these OPENCV params .* bend the image centre beyond any lens"),
    (lambda c: c.update(model="OPENCV", params=[50.0, 50.0, 32.0, 24.0, -600.0, 0.0, 0.0, 0.0]),
     r"bend the image centre beyond any lens"),
])
def test_impossible_lenses_and_sizes_are_refused(tmp_path, edit, words):
    images, rigs_path, data = make_inputs(tmp_path)
    edit(data["rigs"][0]["sensors"]["wide"])
    write_rigs(rigs_path, data)
    expect(tmp_path, r"rig 'rig01' sensor wide: .*" + words, images, rigs_path)


@pytest.mark.parametrize("model,params", [
    ("OPENCV", [50.0, 50.0, 32.0, 24.0, -0.3, 0.1, 0.001, -0.001]),
    ("EUCM", [20.0, 20.0, 32.0, 24.0, 0.6, 1.1]),
    ("FOV", [20.0, 20.0, 32.0, 24.0, 0.9]),
    ("OPENCV_FISHEYE", [13.0, 13.0, 32.0, 24.0, 0.05, -0.01, 0.002, 0.0]),
    ("FULL_OPENCV", [50.0, 50.0, 32.0, 24.0, -0.1, 0.01, 0.0, 0.0, 0.001, 0.0, 0.0, 0.0]),
    ("DIVISION", [50.0, 50.0, 32.0, 24.0, -0.2]),
])
def test_real_lenses_of_every_kind_are_accepted(tmp_path, model, params):
    images, rigs_path, data = make_inputs(tmp_path)
    data["rigs"][0]["sensors"]["wide"].update(model=model, params=params)
    write_rigs(rigs_path, data)
    assert load_inputs(images, rigs_path).rigs[0].wide.model.name == model


@pytest.mark.parametrize("data,words", [
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": "1e308"}]},
     r"camera_distance\[0\]: 'meters' must be a finite number 0.001 - 2000 m, got '1e308': a measured size in "
     r"metres \(millimetres or another unit\?\)"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 1e308}]}, r"'meters' must be a finite"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": math.inf}]}, r"got inf: a measurement is a finite number of metres"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 0}]}, r"got 0: a measured size is more than zero"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": -3}]}, r"got -3: a measured size is more than zero"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 0.005}]},
     r"'meters' = 0.005 m between two rigs, which stand at least 0.01 m apart"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12, "sigma": 1e-300}]},
     r"sigma must be a finite number 0.0001 - 12 m, got 1e-300: a rangefinder's 1-sigma error"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12, "sigma": 20}]}, r"sigma must be"),
    ({"camera_distance": [{"a": "rig01/wide", "b": "rig01/narrow", "meters": 0.06}]},
     r"a = 'rig01/wide' and b = 'rig01/narrow' are the two sensors of one rig; 0.06 m agrees with their "
     r"narrow_from_wide baseline \|t\| = 0.06 m, which fixes it already"),
    ({"camera_distance": [{"a": "rig01/wide/f0.png", "b": "rig01/narrow", "meters": 6}]},
     r"two sensors of one rig; 6 m contradicts their narrow_from_wide baseline \|t\| = 0.06 m"),
    ({"pixel_sigma": 1e-300, "camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 3}]},
     r"pixel_sigma must be a finite number 0.01 - 20 px"),
    (dict(bar(), known_length=[dict(bar()["known_length"][0], sigma=1e-300)]), r"known_length\[0\]: sigma must be"),
    (dict(bar(), known_length=[dict(bar()["known_length"][0], meters=1e308)]), r"known_length\[0\]: 'meters' must"),
])
def test_implausible_measurements_are_refused_saying_why(tmp_path, data, words):
    images, rigs_path, _ = make_inputs(tmp_path)
    expect(tmp_path, words, images, rigs_path, scale_file(tmp_path, data))


@pytest.mark.parametrize("make,words", [
    (lambda: MappingOptions(incremental_time_limit_s=2**31),
     r"--incremental-time-limit \(seconds\) must be an integer >= 0 and <= 2147483647, got 2147483648"),
    (lambda: __import__("rigsfm.track.options", fromlist=["Thresholds"]).Thresholds(translation_mm=math.inf),
     r"--translation-threshold-mm must be a number >= 0 and <= 1e\+06, got inf"),
    (lambda: __import__("rigsfm.track.options", fromlist=["Thresholds"]).Thresholds(rotation_deg=math.nan),
     r"--rotation-threshold-deg must be a number"),
])
def test_options_beyond_what_the_stages_take_are_refused(make, words):
    with pytest.raises(InputError, match=words):
        make()


@pytest.mark.parametrize("height,words", [
    (math.nan, r"--plane-height nan is not a height: give one above the floor in metres"),
    (math.inf, r"--plane-height inf is not a height"),
    (-1.0, r"--plane-height -1 m is below the floor"),
])
def test_plane_height_that_is_no_number_is_named_so(height, words):
    from rigsfm.run.options import WorldOptions
    from rigsfm.run.world.frame import validate_world_options

    with pytest.raises(InputError, match=words):
        validate_world_options(WorldOptions(plane_heights=(height,)))


@pytest.mark.parametrize("out", ["images/out", "images", "images/rig01/wide/out"])
def test_an_output_folder_inside_the_image_folder_is_refused(tmp_path, out):
    from rigsfm.run.pipeline import run

    images, rigs_path, _ = make_inputs(tmp_path)
    where = "is" if out == "images" else "lies inside"  # 'OUT lies inside' itself read wrong
    with pytest.raises(InputError, match=rf"--out \S+ {where} the image folder \S+, whose every folder must be a "
                                         r"rig; choose an output folder outside it"):
        run(images, rigs_path, tmp_path / out, None, RunOptions())
    assert sorted(p.name for p in images.iterdir()) == ["rig01", "rig02"]


def test_priors_check_camera_sigmas_with_rigs_yaml_bounds():
    import pycolmap

    from rigsfm.core.rig import RigCalibration
    from rigsfm.run.adjustment.priors import rig_prior

    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[50.0, 50.0, 32.0, 24.0])
    rig = RigCalibration("rig01", camera, camera, pycolmap.Rigid3d(pycolmap.Rotation3d(), [0.06, 0.0, 0.0]))
    for sigmas, words in (([1e-9, 0.4, 0.5, 0.5], r"the focal length's sigma 1e-09 px must be at least 0.0001 px"),
                          ([0.4, 0.4, 9.0, 0.5], r"the principal point's sigma 9 px must be")):
        with pytest.raises(InputError, match=words):
            rig_prior(rig, RigSigmas(wide=np.array(sigmas)))


def test_a_thousand_rig_file_is_validated_whole(tmp_path):
    """Validation is linear in the rigs (benchmarks: under 1 s for this file); every rig is read and checked."""
    data = with_sigmas({"units": "meters", "rigs": [
        {"name": f"rig{i:04d}", "sensors": {"wide": {"model": "OPENCV", "width": 1624, "height": 1234,
                                                     "params": [900.0, 900.0, 812.0, 617.0, -0.1, 0.01, 0.0, 0.0]},
                                            "narrow": {"model": "OPENCV", "width": 1624, "height": 1234,
                                                       "params": [3600.0, 3600.0, 812.0, 617.0, 0.01, 0.0, 0.0, 0.0]}},
         "narrow_from_wide": {"rotation": np.eye(3).tolist(), "translation": [-0.06, 0.0, 0.001]}}
        for i in range(1000)]})
    for rig in data["rigs"]:
        for sensor in ("wide", "narrow"):
            rig["sensors"][sensor]["sigmas"] = [0.5, 0.5, 0.6, 0.6, 1e-3, 1e-4, 1e-5, 1e-5]
    path = tmp_path / "rigs.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    rigs = load_rigs(path)
    assert [r.name for r in rigs] == [f"rig{i:04d}" for i in range(1000)]
    assert all(r.sigmas.translation_m[2] == 3e-4 for r in rigs)
    data["rigs"][999]["name"] = "rig0000"  # the last rig repeats the first: found in the same pass
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"repeated: 'rig0000' \(rigs\[0\] and rigs\[999\]\)"):
        load_rigs(path)


def test_a_rigs_yaml_too_large_for_any_network_is_refused_before_parsing(tmp_path, monkeypatch):
    import rigsfm.core.rig as rig_module

    images, rigs_path, data = make_inputs(tmp_path)
    with rigs_path.open("a") as f:
        f.write(("# " + "x" * 1022 + "\n") * (33 * 1024))  # 33 MiB of comments: parsing them alone took seconds
    with pytest.raises(InputError, match=r"rig calibration file '\S+' is 33.0 MiB, over the 32 MiB any real one "
                                         r"takes; is it the right file\?"):
        load_rigs(rigs_path)
    write_rigs(rigs_path, data)
    monkeypatch.setattr(rig_module, "MAX_RIGS", 1)
    with pytest.raises(InputError, match=r"rigs.yaml: 2 rigs, more than the 1 any network has; is it the right file"):
        load_rigs(rigs_path)


@pytest.mark.parametrize("scale", [0.05, 0.09])
def test_demo_refuses_an_image_scale_it_cannot_register_before_rendering(tmp_path, scale):
    from rigsfm.synth.demo import MIN_IMAGE_SCALE, run_demo
    from rigsfm.synth.scene import SceneOptions

    assert MIN_IMAGE_SCALE == 0.1
    with pytest.raises(InputError, match=rf"--image-scale {scale:g} is below 0.1, the smallest at which the demo's "
                                         r"rigs register \(162x123 images\); give 0.1 or more"):
        run_demo(tmp_path / "demo", SceneOptions(image_scale=scale))
    assert not (tmp_path / "demo").exists()


def test_demo_refuses_rigs_too_far_apart_to_register_and_warns_where_not_all_may(tmp_path):
    from rigsfm.synth.demo import check_arrangement, run_demo
    from rigsfm.synth.scene import SceneOptions

    with pytest.raises(InputError, match=r"2 rigs round the full circle stand 180 deg apart, where the demo's wide "
                                         r"images share too little to register .*: give --num-rigs 4 or more on the "
                                         r"full circle, or --arc-deg 90 or less"):
        run_demo(tmp_path / "demo", SceneOptions(num_rigs=2, image_scale=0.25))
    assert not (tmp_path / "demo").exists()
    assert check_arrangement(3, 360.0).startswith("DEMO RIGS FAR APART: 3 rigs round the full circle stand 120 deg")
    assert "give --num-rigs 4 or more, or --arc-deg 180 or less" in check_arrangement(3, 270.0)  # 135 deg apart
    assert check_arrangement(4, 360.0) is None and check_arrangement(2, 60.0) is None and check_arrangement(8, 360.0) is None


def test_a_failed_atomic_write_names_the_users_file_not_the_temporary_one(tmp_path):
    from rigsfm.core.io import write_text_atomic

    target = tmp_path / "rigs.yaml"
    target.mkdir()  # the rename onto a folder fails
    (target / "keep").write_text("x")
    with pytest.raises(OSError) as caught:
        write_text_atomic(target, "units: meters\n")
    assert caught.value.filename == str(target) and ".tmp" not in str(caught.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rigs.yaml"]  # the temporary file is gone


def test_manual_matches_name_a_decomposed_rig_folder_in_composed_form(tmp_path):
    from rigsfm.run.matching.manual_matches import validate_manual_matches

    images, rigs_path, composed, decomposed = _nfd_inputs(tmp_path)
    rng = np.random.default_rng(1)
    a, b = rng.uniform(4, 44, (8, 2)), rng.uniform(4, 44, (8, 2))  # spread: no line, no degenerate pose
    rows = [f"{composed}/wide/f0.png,{xa:.2f},{ya:.2f},rig02/wide/f0.png,{xb:.2f},{yb:.2f}"
            for (xa, ya), (xb, yb) in zip(a, b)]
    path = tmp_path / "matches.csv"
    path.write_text("image_a,x_a,y_a,image_b,x_b,y_b\n" + "\n".join(rows) + "\n")
    inputs = load_inputs(images, rigs_path)
    pairs = validate_manual_matches(path, read_manual_matches(path), inputs.images, inputs.rigs)
    assert [set(pair) for pair in pairs] == [{f"{decomposed}/wide/f0.png", "rig02/wide/f0.png"}]


@pytest.mark.parametrize("text", ["", "# only a comment\n", "- rig01\n- rig02\n", "rigs\n"])
def test_an_empty_or_shapeless_input_file_says_how_it_is_written(tmp_path, text):
    """rigs.yaml, scale.yaml and board.yaml that are empty, a list or a word said only 'expected a mapping'."""
    from rigsfm.calibrate.board import load_board_spec
    from rigsfm.core.rig import load_rigs
    from rigsfm.run.inputs.scale_file import load_scale

    for load, name, words in ((load_rigs, "rigs.yaml", "it starts 'units: meters' and 'rigs:'"),
                              (lambda path: load_scale(path, []), "scale.yaml", "'camera_distance:' and/or 'known_length:'"),
                              (load_board_spec, "board.yaml", "it gives 'type:'")):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(InputError, match=r"(is empty|found (the text|a list))") as error:
            load(path)
        assert words in str(error.value), str(error.value)
