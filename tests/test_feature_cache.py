"""RIGSFM_FEATURE_CACHE: features extracted once per image file and settings, read back bit-identical in another
workspace; another setting, another image content or an unreadable entry means a new extraction."""

import logging
import shutil

import cv2
import numpy as np
import pycolmap
import pytest

from rigsfm.run.inputs.database import create_database
from rigsfm.run.matching.extract import extract_features
from rigsfm.run.matching.feature_cache import FEATURE_CACHE_ENV
from rigsfm.run.options import MatchingOptions
from rigsfm.run.pipeline import load_inputs
from rigsfm.synth.scene import SceneOptions

SCENE = SceneOptions(num_rigs=2, arc_deg=60.0, image_scale=0.25, seed=0)  # two wide images of 406x308


def _features(db_path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    with pycolmap.Database.open(db_path) as database:
        return {image.name: (database.read_keypoints(image.image_id), database.read_descriptors(image.image_id).data)
                for image in database.read_all_images() if database.exists_keypoints(image.image_id)}


@pytest.fixture
def extract(tmp_path, caplog):
    """``extract(images, name, options) -> (features per image, how many were extracted, how many came from the
    cache)``: a new workspace's database, as ``rigsfm run`` extracts into it."""
    caplog.set_level(logging.INFO, logger="rigsfm.run.matching.extract")

    def run(images, rigs, name, options=MatchingOptions()):  # noqa: B008 - read, never changed
        inputs = load_inputs(images, rigs)
        db_path = create_database(tmp_path / f"{name}.db", inputs.rigs, inputs.images)
        caplog.clear()
        assert extract_features(db_path, images, inputs.images, options) == 2
        (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Features for 2 images")]
        extracted, cached = (int(line.split(": ")[1].split()[0]), int(line.split(", ")[1].split()[0]))
        return _features(db_path), extracted, cached

    return run


def test_features_come_back_bit_identical_and_only_for_the_same_file_and_settings(rendered, extract, tmp_path,
                                                                                   monkeypatch, caplog):
    dataset = rendered(SCENE)
    cache = tmp_path / "cache"
    monkeypatch.setenv(FEATURE_CACHE_ENV, str(cache))
    first, extracted, cached = extract(dataset.images, dataset.rigs, "first")
    assert (extracted, cached) == (2, 0) and len(list(cache.glob("*.npz"))) == 2
    again, extracted, cached = extract(dataset.images, dataset.rigs, "again")
    assert (extracted, cached) == (0, 2)
    assert first.keys() == again.keys() and len(first) == 2
    for name, (keypoints, descriptors) in first.items():
        assert len(keypoints) > 500
        np.testing.assert_array_equal(again[name][0], keypoints)
        np.testing.assert_array_equal(again[name][1], descriptors)

    # Another setting: extracted again (fewer features), and kept beside the first ones.
    fewer, extracted, cached = extract(dataset.images, dataset.rigs, "fewer", MatchingOptions(max_num_features=300))
    assert (extracted, cached) == (2, 0)
    assert all(len(fewer[name][0]) < len(first[name][0]) / 2 for name in first)
    assert len(list(cache.glob("*.npz"))) == 4

    # Another content under the same name: that image is extracted, the other one read back.
    images = tmp_path / "images"
    shutil.copytree(dataset.images, images)
    changed = images / "rig02" / "wide" / "frame0000.png"
    pixels = cv2.imread(str(changed), cv2.IMREAD_GRAYSCALE)
    pixels[100:110, 100:110] = 255 - pixels[100:110, 100:110]
    cv2.imwrite(str(changed), pixels)
    edited, extracted, cached = extract(images, dataset.rigs, "edited")
    assert (extracted, cached) == (1, 1)
    np.testing.assert_array_equal(edited["rig01/wide/frame0000.png"][0], first["rig01/wide/frame0000.png"][0])

    # An unreadable entry: extracted again and replaced.
    for entry in cache.glob("*.npz"):
        entry.write_bytes(entry.read_bytes()[:100])
    repaired, extracted, cached = extract(dataset.images, dataset.rigs, "repaired")
    assert (extracted, cached) == (2, 0)
    np.testing.assert_array_equal(repaired["rig01/wide/frame0000.png"][1], first["rig01/wide/frame0000.png"][1])
    assert extract(dataset.images, dataset.rigs, "after")[1:] == (0, 2)

    # A cache that cannot be written: the features are extracted all the same, with a warning.
    monkeypatch.setenv(FEATURE_CACHE_ENV, str(tmp_path / "not_a_folder"))
    (tmp_path / "not_a_folder").write_text("")
    assert extract(dataset.images, dataset.rigs, "unwritable")[1:] == (2, 0)
    assert sum("not written" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records) == 2
    monkeypatch.setenv(FEATURE_CACHE_ENV, str(cache))

    # Without the variable nothing is read or written.
    monkeypatch.delenv(FEATURE_CACHE_ENV)
    before = sorted((p.name, p.stat().st_mtime_ns) for p in cache.iterdir())
    assert extract(dataset.images, dataset.rigs, "off")[1:] == (2, 0)
    assert sorted((p.name, p.stat().st_mtime_ns) for p in cache.iterdir()) == before


def test_a_stage_with_everything_kept_reports_itself_done(rendered, tmp_path):
    """A re-run whose features and matches are all in the database reports each stage complete: before, neither
    counted anything, and their bars kept '0/?' and a running clock for the whole run."""
    from rigsfm.run.matching.match import match_features

    dataset = rendered(SCENE)
    inputs = load_inputs(dataset.images, dataset.rigs)
    db_path = create_database(tmp_path / "db.db", inputs.rigs, inputs.images)
    options = MatchingOptions()
    extract_features(db_path, dataset.images, inputs.images, options)
    match_features(db_path, inputs.images, options, tmp_path / "pairs.txt")
    reports: dict[str, list] = {"features": [], "matching": []}
    extract_features(db_path, dataset.images, inputs.images, options,
                     lambda done, total: reports["features"].append((done, total)))
    match_features(db_path, inputs.images, options, tmp_path / "pairs.txt",
                   lambda done, total: reports["matching"].append((done, total)))
    assert reports == {"features": [(2, 2)], "matching": [(1, 1)]}, reports
