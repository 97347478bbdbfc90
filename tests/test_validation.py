"""Inputs that used to run to the end silently wrong, or fail after the heavy work with a misleading message, are
refused at validation with one line naming the file, the rig or entry, the key and the fix."""

import copy
import json
import logging
import math

import numpy as np
import pytest
import yaml

from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.rig import RigSigmas, load_rigs, write_rigs as write_rig_file
from rigsfm.core.workspace import Workspace, read_json, read_model
from rigsfm.run.manual_matches import ManualMatchError, read_manual_matches
from rigsfm.run.options import AdjustOptions, MappingOptions, MatchingOptions, RunOptions
from rigsfm.run.pipeline import load_inputs
from test_bad_input import H, W, expect, write_rigs
from test_bad_input import make_inputs as make_aliased_inputs

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
    ([-60.0, 0.0, 0.0], r"rig rig02 narrow_from_wide translation: the baseline \|t\| = 60 m is outside 1 mm - 5 m "
                        r"\(in millimetres\? 60 mm is 0.06 m\); give the translation in metres"),
    ([0.0, 0.0, 0.0], r"rig rig02 narrow_from_wide translation: the baseline \|t\| = 0 m .*cannot be at one point"),
    ([0.0004, 0.0, 0.0], r"rig rig02 narrow_from_wide translation: .*0.0004 m is outside"),
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
    ([50.0, 50.0, 64.5, 24.0], r"rig rig01 sensor narrow: principal point \(64.5, 24\) lies outside the 64x48 image"),
    ([50.0, 50.0, 32.0, -1.0], r"principal point \(32, -1\) lies outside"),
    ([4.0, 4.0, 32.0, 24.0], r"rig rig01 sensor narrow: focal length fx = 4 px is 0.0625 x the image width 64; a lens "
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
    ("rig", "narow_from_wide", r"rig rig02: unknown key 'narow_from_wide' \(did you mean 'narrow_from_wide'\?\)"),
    ("camera", "param", r"rig rig02 sensor wide: unknown key 'param' \(did you mean 'params'\?\)"),
    ("pose", "tranlsation", r"rig rig02 narrow_from_wide: unknown key 'tranlsation' \(did you mean 'translation'\?\)"),
    ("pose", "sigma_rotation", r"unknown key 'sigma_rotation' \(did you mean 'sigma_rotation_deg'\?\)"),
    ("sensors", "wide2", r"rig rig02 sensors: unknown key 'wide2' \(did you mean 'wide'\?\)"),
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
    assert any(f"rig rig02 has no narrow images ({images / 'rig02' / 'narrow'} does not exist)" in r.message
               for r in caplog.records), caplog.text


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
     r"rig rig02 sensor wide sigmas \(one per entry of params\): expected 4 finite numbers >= 0"),
    (lambda r: r["sensors"]["wide"].update(sigmas=[0.4, float("nan"), 0.5, 0.5]), r"sensor wide sigmas .*finite"),
    (lambda r: r["sensors"]["narrow"].update(sigmas=[0.0, 0.4, 0.5, 0.5]),
     r"rig rig02 sensor narrow sigmas .*the focal length's sigma 0 px must be > 0 and at most 10 % of 50 px"),
    (lambda r: r["sensors"]["narrow"].update(sigmas=[6.0, 0.4, 0.5, 0.5]),
     r"the focal length's sigma 6 px must be > 0 and at most 10 %"),
    (lambda r: r["sensors"]["wide"].update(sigmas=[0.4, 0.4, 9.0, 0.5]), r"the principal point's sigma 9 px"),
    (lambda r: r["narrow_from_wide"].update(sigma_rotation_deg=[0.02, 6.0, 0.01]),
     r"rig rig02 narrow_from_wide sigma_rotation_deg: each must be > 0 and at most 5 degrees"),
    (lambda r: r["narrow_from_wide"].update(sigma_rotation_deg=[0.02, 0.0, 0.01]), r"sigma_rotation_deg: each must be > 0"),
    (lambda r: r["narrow_from_wide"].update(sigma_translation_m=[0.1, 0.0, 0.0]),
     r"rig rig02 narrow_from_wide sigma_translation_m: each must be > 0 and below the baseline \|t\| = 0.06 m"),
    (lambda r: r["narrow_from_wide"].update(covariance=(np.eye(6) * 0.01).tolist()),
     r"rig rig02 narrow_from_wide covariance: a rotation variance above \(5 deg\)\^2"),
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
    (bar(b1=(40, H + 3)), r"known_length\[0\].observations\[1\].b: \(40, 51\) lies outside rig02/wide/f0.png, "
                          r"which is 64x48 px .*fix the coordinates"),
    (bar(a0=(-2, 10)), r"known_length\[0\].observations\[0\].a: \(-2, 10\) lies outside rig01/wide/f0.png"),
    (bar(image1="rig02/narrow/f0.png", a1=(70, 5)), r"observations\[1\].a: \(70, 5\) lies outside rig02/narrow/f0.png"),
    (bar(a1=(30, 20), b1=(30.4, 20.2)), r"known_length\[0\].observations\[1\]: a and b are the same point in "
                                        r"rig02/wide/f0.png \(a zero-length bar\)"),
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
    with pytest.raises(WorkspaceError, match=r"sparse/images.bin is truncated or damaged \(20 B; says 2 images but "
                                             r"only 12 B follow\): re-run `rigsfm run IMAGES"):
        Workspace(tmp_path / "out").read_sparse()
    (sparse / "images.bin").unlink()
    with pytest.raises(WorkspaceError, match=r"sparse holds no complete COLMAP model \(images.bin missing\): fix"):
        read_model(sparse, "fix")


@pytest.mark.parametrize("text,words", [
    ('{"narrow": [], "pairs": [', r"narrow_poses.json is not valid JSON \(.*\): re-run `rigsfm run"),
    ("[]", r"narrow_poses.json is not a file rigsfm wrote \(no narrow, pairs\)"),
    ("\udcff", r"narrow_poses.json is not valid JSON"),
])
def test_a_damaged_json_file_names_itself(tmp_path, text, words):
    workspace = Workspace(tmp_path)
    workspace.narrow_poses.write_bytes(text.encode("utf-8", "surrogateescape"))
    with pytest.raises(WorkspaceError, match=words):
        workspace.read_narrow_poses()
    with pytest.raises(WorkspaceError, match=r"nothing.json is missing: fix"):
        read_json(tmp_path / "nothing.json", "fix")
