"""A fuzzing net under every parser of user input: whatever the input, a result or an InputError (a RigsfmError
for the picker's answers), never another exception.

Inputs are mutations of valid files (a key or value replaced, deleted or added anywhere in the tree, with numbers
from NaN to 10^400, strings, lists and mappings), plus arbitrary text; for the picker, random JSON bodies and
queries against a real PickerServer on 127.0.0.1. 100-200 examples per parser, 5-20 s each here.
"""

import copy
import io
import json
import math
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rigsfm.core.errors import InputError, RigsfmError
from rigsfm.core.io import parse_yaml
from rigsfm.core.rig import load_rigs
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.inputs.scale_file import load_scale
from rigsfm.run.matching.manual_matches import read_manual_matches, validate_manual_matches

pytestmark = pytest.mark.slow  # hypothesis examples by the hundred (`-m 'not slow'` skips them)

HEALTH = [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=HEALTH)
FUZZ_YAML = settings(max_examples=100, deadline=None, suppress_health_check=HEALTH)  # PyYAML parses ~10 ms a file

W, H = 640, 480
CAMERA = {"model": "OPENCV", "width": W, "height": H, "params": [500.0, 501.0, 320.5, 240.5, -0.1, 0.01, 0.0, 0.0],
          "sigmas": [0.5, 0.5, 0.6, 0.6, 0.001, 0.002, 1e-4, 1e-4]}
RIGS = {"units": "meters", "rigs": [
    {"name": name, "sensors": {"wide": copy.deepcopy(CAMERA), "narrow": dict(copy.deepcopy(CAMERA),
                                                                               params=[2000.0, 2000.0, 320.5, 240.5,
                                                                                       0.0, 0.0, 0.0, 0.0])},
     "narrow_from_wide": {"rotation": np.eye(3).tolist(), "translation": [-0.06, 0.0, 0.001],
                          "sigma_rotation_deg": [0.01, 0.02, 0.01], "sigma_translation_m": [1e-4, 1e-4, 3e-4],
                          "covariance": (np.diag([3e-8, 1e-7, 3e-8, 1e-8, 1e-8, 9e-8])).tolist()}}
    for name in ("rig01", "rig02")]}
SCALE = {"pixel_sigma": 0.5,
         "camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12.5, "sigma": 0.01}],
         "known_length": [{"meters": 2.0, "sigma": 0.002, "observations": [
             {"image": "rig01/wide/f0.png", "a": [100.0, 200.0], "b": [150.0, 210.0]},
             {"image": "rig02/wide/f0.png", "a": [300.0, 220.0], "b": [350.5, 230.0]}]}]}

LEAVES = st.one_of(st.none(), st.booleans(), st.integers(), st.integers(min_value=-(10**400), max_value=10**400),
                   st.floats(), st.text(max_size=12), st.sampled_from(["rig01", "rig01/wide", "rig01/wide/f0.png",
                                                                       "OPENCV", "meters", "wide", "narrow"]))
VALUES = st.recursive(LEAVES, lambda inner: st.lists(inner, max_size=5)
                      | st.dictionaries(st.text(max_size=10) | st.integers(), inner, max_size=4), max_leaves=16)


def paths(node, prefix=()):
    """Every node of a tree of dicts and lists, as the key path to it (the root is ())."""
    yield prefix
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in items:
        yield from paths(child, (*prefix, key))


@st.composite
def mutated(draw, base):
    """``base`` with 1-3 random edits at nodes drawn uniformly from the whole tree: a node replaced, deleted, or
    given a new key or item."""
    data = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(list(paths(data))))
        if not path:
            data = draw(VALUES)
            continue
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        key = path[-1]
        action = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        if action == "replace":
            parent[key] = draw(VALUES)
        elif action == "delete":
            del parent[key]
        elif isinstance(parent[key], dict):
            parent[key][draw(st.text(max_size=12))] = draw(VALUES)
        elif isinstance(parent[key], list):
            parent[key].append(draw(VALUES))
        else:
            parent[key] = [parent[key], draw(VALUES)]
    return data


def dump(value) -> str:
    return yaml.safe_dump(value, sort_keys=False, allow_unicode=True)


TEXT = st.one_of(st.text(max_size=300), st.binary(max_size=300).map(lambda b: b.decode("latin-1")),
                 st.integers(1, 3000).map(lambda n: "rigs: " + "[" * n + "]" * n))  # recursion in the YAML parser


def documents(base):
    """Mutated valid files as YAML (or JSON) text, and arbitrary text."""
    return st.one_of(mutated(base).map(dump), mutated(base).map(lambda v: json.dumps(v, allow_nan=True)), TEXT)


def test_the_valid_files_are_valid(tmp_path):
    for document in (RIGS, SCALE):  # libyaml's parser (rigsfm's where PyYAML has it) reads what PyYAML's own reads
        assert parse_yaml(dump(document)) == yaml.safe_load(dump(document)) == document
    rigs = tmp_path / "rigs.yaml"
    rigs.write_text(dump(RIGS))
    loaded = load_rigs(rigs)
    assert [r.name for r in loaded] == ["rig01", "rig02"] and loaded[0].sigmas.covariance.shape == (6, 6)
    scale = tmp_path / "scale.yaml"
    scale.write_text(dump(SCALE))
    assert load_scale(scale, IMAGES, loaded).known_lengths[0].meters == 2.0


def test_an_image_side_beyond_a_float_is_an_input_error(tmp_path):
    """An integer side too large for a float (hypothesis drew a height of ~10^400) is refused as out of range, not
    with an OverflowError's traceback."""
    document = copy.deepcopy(RIGS)
    document["rigs"][0]["sensors"]["narrow"]["height"] = 10 ** 400
    path = tmp_path / "rigs.yaml"
    path.write_text(dump(document))
    with pytest.raises(InputError, match="height must be a whole number of pixels"):
        load_rigs(path)


@FUZZ_YAML
@given(text=documents(RIGS))
def test_rigs_yaml_gives_rigs_or_an_input_error(tmp_path, text):
    path = tmp_path / "rigs.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    try:
        rigs = load_rigs(path)
    except InputError:
        return
    for rig in rigs:  # what is accepted is usable: finite, plausible, a proper rotation
        assert 0.001 <= np.linalg.norm(rig.narrow_from_wide.translation) <= 5.0
        for camera in (rig.wide, rig.narrow):
            assert np.all(np.isfinite(camera.params)) and 0 <= camera.principal_point_x <= camera.width


IMAGES = [ImageEntry(rig, sensor, "f0.png", None) for rig in ("rig01", "rig02") for sensor in ("wide", "narrow")]


@FUZZ_YAML
@given(text=documents(SCALE))
def test_scale_yaml_gives_a_scale_or_an_input_error(tmp_path, text):
    path = tmp_path / "scale.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    rigs_path = tmp_path / "rigs.yaml"
    rigs_path.write_text(dump(RIGS))
    try:
        spec = load_scale(path, IMAGES, load_rigs(rigs_path))
    except InputError:
        return
    for item in spec.known_lengths:
        assert item.meters > 0 and math.isfinite(item.meters)
        for obs in item.observations:
            assert all(0 <= v <= max(W, H) for v in (*obs.a, *obs.b))


CSV_ROW = st.tuples(st.sampled_from(["rig01/wide/f0.png", "rig02/wide/f0.png", "rig01/narrow/f0.png", "x", ""]),
                    st.one_of(st.floats(), st.text(max_size=6)), st.one_of(st.floats(), st.integers()),
                    st.sampled_from(["rig02/wide/f0.png", "rig01/wide/f0.png", "rig03/wide/f0.png"]),
                    st.floats(-10, 700), st.floats(-10, 500))
CSV_TEXT = st.one_of(
    st.lists(CSV_ROW, max_size=12).map(lambda rows: "image_a,x_a,y_a,image_b,x_b,y_b\n"
                                       + "".join(",".join(str(c) for c in row) + "\n" for row in rows)),
    TEXT)


@FUZZ
@given(text=CSV_TEXT, encoding=st.sampled_from(["utf-8", "utf-8-sig", "utf-16", "utf-16-le", "latin-1"]))
def test_matches_csv_gives_correspondences_or_an_input_error(tmp_path, text, encoding):
    from rigsfm.core.rig import load_rigs as read_rigs

    path = tmp_path / "matches.csv"
    path.write_bytes(text.encode(encoding, errors="replace"))
    rigs_path = tmp_path / "rigs.yaml"
    rigs_path.write_text(dump(RIGS))
    try:
        rows = read_manual_matches(path)
        validate_manual_matches(path, rows, IMAGES, read_rigs(rigs_path))
    except InputError:
        return


# --- the picker's HTTP API -----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def picker(tmp_path_factory):
    from rigsfm.pick.server import PickerServer
    from rigsfm.pick.session import PickerSession, picker_image

    root = tmp_path_factory.mktemp("picker")
    rng = np.random.default_rng(0)
    paths = []
    for rig in ("rig01", "rig02"):
        path = root / "images" / rig / "wide" / "f0.png"
        path.parent.mkdir(parents=True)
        cv2.imwrite(str(path), rng.integers(0, 255, (H, W), dtype=np.uint8))
        paths.append(path)
    rigs = root / "rigs.yaml"
    rigs.write_text(dump(RIGS))
    loaded = load_rigs(rigs)
    session = PickerSession(picker_image(paths[0], loaded), picker_image(paths[1], loaded), root / "matches.csv")
    server = PickerServer(session)
    yield server
    server.close()


def request(server, method: str, path: str, body: bytes | None = None, headers: dict | None = None):
    req = urllib.request.Request(server.url.rstrip("/") + path, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=30) as answer:
            return answer.status, json.loads(answer.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


PAIR = st.lists(st.one_of(st.floats(-50, 700), st.floats(), st.integers(), st.text(max_size=3), st.none()),
                min_size=0, max_size=6)
BODIES = st.one_of(
    st.fixed_dictionaries({"pairs": st.lists(PAIR, max_size=10)}),
    st.fixed_dictionaries({"pairs": VALUES}),
    VALUES)


@FUZZ
@given(body=BODIES)
def test_picker_put_answers_every_json_body(picker, body):
    status, answer = request(picker, "PUT", "/api/pairs", json.dumps(body, allow_nan=True).encode(),
                             {"Content-Type": "application/json"})
    assert status in (200, 400), (status, answer)
    if status == 200:
        assert isinstance(answer["pairs"], list)
        assert all(math.isfinite(v) for p in answer["pairs"] for v in p["a"] + p["b"])
    else:
        assert isinstance(answer["error"], str) and answer["error"]
    status, state = request(picker, "GET", "/api/state")
    assert status == 200 and "pairs" in state  # the server is still there


@FUZZ
@given(raw=st.binary(max_size=200), length=st.one_of(st.none(), st.sampled_from(["-1", "abc", "0", "99999999"])))
def test_picker_put_answers_raw_bytes(picker, raw, length):
    headers = {"Content-Type": "application/json"}
    if length is not None:
        headers["Content-Length"] = length if length != "99999999" else str(len(raw))
    status, answer = request(picker, "PUT", "/api/pairs", raw, headers)
    assert status in (200, 400, 413), (status, answer)


@FUZZ
@given(side=st.text(max_size=3), x=st.text(max_size=8) | st.floats().map(str), y=st.floats().map(str))
def test_picker_epipolar_query_answers(picker, side, x, y):
    from urllib.parse import urlencode

    status, answer = request(picker, "GET", "/api/epipolar?" + urlencode({"side": side, "x": x, "y": y}))
    assert status in (200, 400), (status, answer)


def test_picker_errors_are_rigsfm_errors(picker):
    """The session's own checks raise RigsfmError (the server answers them with 400)."""
    with pytest.raises(RigsfmError):
        picker.session.set_pairs([[1.0, 2.0, "x", 4.0]])
    with pytest.raises(RigsfmError):
        picker.session.set_pairs({"a": 1})


# --- keys given twice, Unicode spellings, what is not a regular file ---------------------------------------------

@st.composite
def duplicated_line(draw, base):
    """``base`` as YAML with one of its lines repeated right after itself (a key given twice where it is a key)."""
    lines = dump(base).splitlines(keepends=True)
    k = draw(st.integers(0, len(lines) - 1))
    return "".join(lines[:k + 1] + [lines[k]] + lines[k + 1:])


def mapping_keys_unique(text: str) -> bool:
    """Whether every mapping of the YAML ``text`` gives each key once (PyYAML's own nodes, no rigsfm code)."""
    def unique(node) -> bool:
        if isinstance(node, yaml.MappingNode):
            keys = [k.value for k, _ in node.value]
            return len(keys) == len(set(keys)) and all(unique(v) for _, v in node.value)
        if isinstance(node, yaml.SequenceNode):
            return all(unique(v) for v in node.value)
        return True

    return unique(yaml.compose(text))


@FUZZ_YAML
@given(text=st.one_of(duplicated_line(RIGS), duplicated_line(SCALE)))
def test_a_key_given_twice_is_never_silently_dropped(tmp_path, text):
    path = tmp_path / "input.yaml"
    path.write_text(text)
    try:
        if text.startswith("units"):
            load_rigs(path)
        else:
            rigs_path = tmp_path / "rigs.yaml"
            rigs_path.write_text(dump(RIGS))
            load_scale(path, IMAGES, load_rigs(rigs_path))
    except InputError as error:
        if not mapping_keys_unique(text):
            assert "is given twice" in str(error)
        return
    assert mapping_keys_unique(text)  # accepted: no key was repeated (a list item may be)


NAMES = st.text(st.characters(codec="utf-8", exclude_categories=("Cs", "Cc", "Zl", "Zp")), min_size=1,
                max_size=8).filter(lambda n: "/" not in n and "\\" not in n and not n.startswith(".")
                                   and n.strip() == n and len(n.encode()) < 200)


@FUZZ_YAML
@given(names=st.lists(NAMES, min_size=2, max_size=3, unique_by=lambda n: __import__("unicodedata").normalize("NFC", n)),
       folder_form=st.sampled_from(["NFC", "NFD"]), file_form=st.sampled_from(["NFC", "NFD"]))
def test_rig_names_match_their_folders_in_any_unicode_form(tmp_path_factory, names, folder_form, file_form):
    import unicodedata

    from rigsfm.run.pipeline import load_inputs

    root = tmp_path_factory.mktemp("nfd")
    data = copy.deepcopy(RIGS)
    data["rigs"] = [dict(copy.deepcopy(RIGS["rigs"][0]), name=unicodedata.normalize(file_form, n)) for n in names]
    image = np.zeros((H, W), np.uint8)
    for name in names:
        folder = root / "images" / unicodedata.normalize(folder_form, name) / "wide"
        folder.mkdir(parents=True)
        ok, png = cv2.imencode(".png", image)
        (folder / "f0.png").write_bytes(png.tobytes())
    (root / "rigs.yaml").write_text(dump(data))
    inputs = load_inputs(root / "images", root / "rigs.yaml")
    assert [r.name for r in inputs.rigs] == [unicodedata.normalize(folder_form, n) for n in names]
    assert all((root / "images" / e.name).is_file() for e in inputs.images)


def _make_non_regular(path, kind):
    import os
    import socket

    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        os.symlink("/dev/null", path)
    elif kind == "socket":
        server = socket.socket(socket.AF_UNIX)
        server.bind(str(path))
        return server
    elif kind == "folder":
        path.mkdir()
    elif kind == "loop":
        os.symlink(path.name, path)
    elif kind == "broken":
        os.symlink("missing", path)
    return None


@FUZZ
@given(kind=st.sampled_from(["fifo", "device", "socket", "folder", "loop", "broken"]),
       rig=st.sampled_from(["rig01", "rig02"]), sensor=st.sampled_from(["wide", "narrow"]),
       name=st.sampled_from(["f1.png", "f0.jpg", "x.TIFF", "notes.txt", "f1"]))
def test_what_is_not_a_regular_file_is_refused_or_ignored_never_read(tmp_path_factory, kind, rig, sensor, name):
    import threading

    from rigsfm.run.inputs.images import IMAGE_SUFFIXES
    from rigsfm.run.pipeline import load_inputs

    root = tmp_path_factory.mktemp("special")
    image = np.zeros((H, W), np.uint8)
    for r in ("rig01", "rig02"):
        for s in ("wide", "narrow"):
            (root / "images" / r / s).mkdir(parents=True)
            cv2.imwrite(str(root / "images" / r / s / "f0.png"), image)
    (root / "rigs.yaml").write_text(dump(RIGS))
    held = _make_non_regular(root / "images" / rig / sensor / name, kind)
    outcome = {}

    def load():
        try:
            outcome["inputs"] = load_inputs(root / "images", root / "rigs.yaml")
        except InputError as error:
            outcome["error"] = str(error)

    thread = threading.Thread(target=load, daemon=True)  # a FIFO that is read blocks forever: a daemon is left
    thread.start()
    thread.join(60)
    if held is not None:
        held.close()
    assert outcome, "validation blocked (reading a FIFO?)"
    image_like = "." in name and "." + name.rsplit(".", 1)[1].lower() in IMAGE_SUFFIXES
    if image_like or kind == "folder":
        assert name in outcome.get("error", "")  # refused, naming the file
    else:
        assert "inputs" in outcome


@FUZZ
@given(name=st.text(alphabet=st.sampled_from("[]/\\@:=#*_`~ab1 .éß"), min_size=1, max_size=24))
def test_messages_with_markup_characters_print_verbatim(name):
    """Whatever a message holds (Rich markup's brackets and slashes, backslashes, emphasis marks), the CLI's error
    line shows it exactly, on one line, and printing it never raises."""
    from rich.console import Console

    from rigsfm.cli import common

    message = f"image folder '{name}' does not exist; check the path"
    console = Console(width=40, record=True, file=io.StringIO(), color_system=None)
    original, common.err_console = common.err_console, console
    try:
        common.say_error(message)
    finally:
        common.err_console = original
    assert console.export_text() == f"error: {message}\n"


@st.composite
def damaged_exif(draw):
    """A small JPEG or PNG with an EXIF block whose Orientation is any 16-bit value, then cut, extended or with
    bytes changed anywhere in its header."""
    from support import tag_orientation

    suffix = draw(st.sampled_from([".jpg", ".png"]))
    ok, data = cv2.imencode(suffix, np.full((8, 8), 128, np.uint8))
    assert ok
    data = bytearray(tag_orientation(data.tobytes(), draw(st.integers(0, 0xFFFF)), draw(st.booleans())))
    for _ in range(draw(st.integers(0, 4))):
        data[draw(st.integers(0, min(len(data), 80) - 1))] = draw(st.integers(0, 255))
    cut = draw(st.one_of(st.none(), st.integers(0, len(data))))
    return suffix, bytes(data if cut is None else data[:cut])


@FUZZ
@given(case=damaged_exif())
def test_exif_orientation_of_any_header_is_a_tag_or_none(tmp_path, case):
    """A damaged or odd EXIF header gives an orientation 1-8 or None (no tag to act on), never an exception; the
    refusal is an InputError exactly for the orientations that turn or mirror the image."""
    from rigsfm.core.image_files import exif_orientation, is_turned, refuse_turned_images

    suffix, data = case
    path = tmp_path / f"f0{suffix}"
    path.write_bytes(data)
    orientation = exif_orientation(path)
    assert orientation is None or 1 <= orientation <= 8
    assert exif_orientation(data) == orientation
    try:
        refuse_turned_images([path], folder=tmp_path)
    except InputError as error:
        assert is_turned(orientation) and path.name in str(error)
    else:
        assert not is_turned(orientation)
