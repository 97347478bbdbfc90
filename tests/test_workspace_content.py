"""A workspace recognises its input images by their content: an image whose file changed under the same name loses
its features and matches (and only it), and a damaged, emptied or removed ``database.db`` is made again or named
with the fix instead of an internal error."""

import logging
import os
import shlex
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from bad_inputs_table import RUN, inputs

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.workspace import MARKER, Workspace
from rigsfm.run.inputs.database import check_database_kept, create_database
from rigsfm.run.matching.extract import extract_features
from rigsfm.run.matching.match import match_features
from rigsfm.run.matching.reuse import drop_changed_images
from rigsfm.run.options import MatchingOptions
from rigsfm.run.pipeline import load_inputs
from rigsfm.synth.scene import SceneOptions

REPO = Path(__file__).resolve().parents[1]
SCENE = SceneOptions(num_rigs=3, arc_deg=60.0, image_scale=0.25, seed=0)  # three wide images of 406x308
CHANGED = "rig02/wide/frame0000.png"


def _work(db_path: Path) -> tuple[dict[str, np.ndarray], dict[tuple[str, str], np.ndarray]]:
    """Keypoints per image and verified inlier matches per pair of image names."""
    with pycolmap.Database.open(db_path) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        keypoints = {name: database.read_keypoints(image_id) for image_id, name in names.items()
                     if database.exists_keypoints(image_id)}
        pairs = {}
        for pair_id, geometry in zip(*database.read_two_view_geometries()):
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            pairs[(names[id1], names[id2])] = np.asarray(geometry.inlier_matches)
    return keypoints, pairs


def test_a_changed_image_loses_its_features_and_matches_and_only_it(rendered, tmp_path, caplog):
    dataset = rendered(SCENE)
    images = tmp_path / "images"
    shutil.copytree(dataset.images, images)
    workspace = Workspace(tmp_path / "out")
    workspace.root.mkdir()
    scene = load_inputs(images, dataset.rigs)
    create_database(workspace.database, scene.rigs, scene.images)
    assert drop_changed_images(workspace.database, workspace.image_contents, scene.images) == []
    extract_features(workspace.database, images, scene.images, MatchingOptions())
    match_features(workspace.database, scene.images, MatchingOptions(), workspace.pairs)
    keypoints, pairs = _work(workspace.database)
    assert len(keypoints) == 3 and sum(len(m) > 0 for m in pairs.values()) >= 2
    assert any(CHANGED in pair for pair in pairs) and any(CHANGED not in pair for pair in pairs)

    # The same bytes under another folder: nothing is redone.
    assert drop_changed_images(workspace.database, workspace.image_contents, scene.images) == []
    path = images / CHANGED
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.roll(image, 12, axis=1))  # the rig turned: a new recording under the same name
    caplog.set_level(logging.WARNING, logger="rigsfm.run.matching.extract")
    assert drop_changed_images(workspace.database, workspace.image_contents, scene.images) == [CHANGED]
    assert (f"1 image changed since the last run in this workspace ({CHANGED}): its features and matches are made "
            "again") in caplog.text
    kept_keypoints, kept_pairs = _work(workspace.database)
    assert set(kept_keypoints) == set(keypoints) - {CHANGED}
    for name, array in kept_keypoints.items():
        np.testing.assert_array_equal(array, keypoints[name])
    assert set(kept_pairs) == {pair for pair in pairs if CHANGED not in pair}
    for pair, matches in kept_pairs.items():
        np.testing.assert_array_equal(matches, pairs[pair])
    with pycolmap.Database.open(workspace.database) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        assert not database.exists_descriptors(ids[CHANGED])
        assert not any(database.exists_matches(ids[CHANGED], other) for other in ids.values())

    # Extraction and matching redo the changed image alone; the record now holds its new content.
    assert extract_features(workspace.database, images, scene.images, MatchingOptions()) == 1
    assert match_features(workspace.database, scene.images, MatchingOptions(), workspace.pairs) == sum(
        CHANGED in pair for pair in pairs)
    new_keypoints, _ = _work(workspace.database)
    assert not np.array_equal(new_keypoints[CHANGED][:, :2], keypoints[CHANGED][:, :2])
    caplog.clear()
    assert drop_changed_images(workspace.database, workspace.image_contents, scene.images) == []
    assert "changed" not in caplog.text

    # Without the record what the work was made from is unknown: all of it is made again, said once.
    workspace.image_contents.unlink()
    cleared = drop_changed_images(workspace.database, workspace.image_contents, scene.images)
    assert sorted(cleared) == sorted(keypoints)
    assert f"{workspace.image_contents} holds no record of what the features and matches of 3 images" in caplog.text
    assert _work(workspace.database) == ({}, {})


# --- database.db damaged, emptied, removed -------------------------------------------------------------------------


def _small(root: Path):
    inputs(root)
    return load_inputs(root / "images", root / "rigs.yaml")


@pytest.mark.parametrize("damage,words", [
    (lambda db: db.write_bytes(b"not a database\n" * 300), "is not a database"),
    (lambda db: db.write_bytes(db.read_bytes()[: db.stat().st_size // 2]), "is damaged (database disk image is malformed)"),
    (lambda db: db.write_bytes(b""), "is empty"),
    (lambda db: db.unlink() or pycolmap.Database.open(db).close(), "holds no images"),  # what COLMAP makes after a removal
])
def test_a_damaged_or_emptied_database_is_made_again(tmp_path, caplog, damage, words):
    scene = _small(tmp_path)
    db = tmp_path / "out" / "database.db"
    db.parent.mkdir()
    create_database(db, scene.rigs, scene.images)
    (tmp_path / "out" / "database.db-journal").write_bytes(b"a journal of the damaged file")
    damage(db)
    caplog.set_level(logging.WARNING, logger="rigsfm.run.inputs.database")
    create_database(db, scene.rigs, scene.images)
    assert f"'{db}' {words}" in caplog.text and "it is made again, and so are its features and matches" in caplog.text
    assert not (tmp_path / "out" / "database.db-journal").exists()  # never applied to the new file
    with pycolmap.Database.open(db) as database:
        assert sorted(image.name for image in database.read_all_images()) == sorted(e.name for e in scene.images)
        assert database.num_rigs() == 2


def test_a_database_of_other_inputs_is_made_again_with_overwrite_and_named_without(tmp_path, caplog):
    """Images added to the image folder, or rigs.yaml edited, then `run --overwrite`: the run stopped with 'holds
    other images than the image folder (e.g. <the added image>)' and told the user to delete database.db."""
    import dataclasses

    scene = _small(tmp_path)
    db = tmp_path / "out" / "database.db"
    db.parent.mkdir()
    create_database(db, scene.rigs, scene.images[:-1])
    added = scene.images[-1].name
    with pytest.raises(WorkspaceError, match=rf"database.db' was made from other images \({added} is in the image "
                                             r"folder but not in it\): pass --overwrite to start again from these "
                                             r"inputs, re-run with the inputs of the interrupted run to resume it"):
        create_database(db, scene.rigs, scene.images)
    caplog.set_level(logging.WARNING, logger="rigsfm.run.inputs.database")
    create_database(db, scene.rigs, scene.images, overwrite=True)
    assert "was made from other images" in caplog.text and "it is made again" in caplog.text
    with pycolmap.Database.open(db) as database:
        assert sorted(image.name for image in database.read_all_images()) == sorted(e.name for e in scene.images)
    rig = scene.rigs[0]
    wide = pycolmap.Camera(model=rig.wide.model, width=rig.wide.width, height=rig.wide.height,
                           params=rig.wide.params * 1.01)
    edited = [dataclasses.replace(rig, wide=wide), *scene.rigs[1:]]
    with pytest.raises(WorkspaceError, match=rf"was made with another calibration for {rig.name}/wide \(rigs.yaml "
                                             r"changed\): pass --overwrite"):
        create_database(db, edited, scene.images)
    create_database(db, edited, scene.images, overwrite=True)
    with pycolmap.Database.open(db) as database:
        cameras = {c.camera_id: c for c in database.read_all_cameras()}
        image = next(im for im in database.read_all_images() if im.name.startswith(f"{rig.name}/wide/"))
        assert np.allclose(cameras[image.camera_id].params, wide.params)


def test_a_database_rigsfm_did_not_write_is_refused_and_kept(tmp_path):
    scene = _small(tmp_path)
    db = tmp_path / "database.db"
    with sqlite3.connect(db) as connection:
        connection.execute("CREATE TABLE notes (text TEXT)")
    before = db.read_bytes()
    with pytest.raises(WorkspaceError, match=r"database.db' is not a COLMAP database \(rigsfm did not write it\); "
                                             "choose another --out or move it away"):
        create_database(db, scene.rigs, scene.images)
    assert db.read_bytes() == before


def test_a_database_removed_while_a_run_wrote_it_is_named(tmp_path):
    scene = _small(tmp_path)
    db = tmp_path / "database.db"
    create_database(db, scene.rigs, scene.images)
    check_database_kept(db, scene.images)
    db.unlink()
    words = r"database.db was removed or replaced while this run wrote it: re-run the same command"
    with pytest.raises(WorkspaceError, match=words):
        check_database_kept(db, scene.images)
    pycolmap.Database.open(db).close()  # COLMAP's next stage opens the path: an empty database
    with pytest.raises(WorkspaceError, match=words):
        check_database_kept(db, scene.images)


def test_the_warning_reaches_the_terminal_while_colmap_logs_to_out(tmp_path):
    """The stages' warnings are rigsfm's to the user: printed on the command's stderr, not only in colmap.log
    (where COLMAP's own log goes, through the same file descriptor)."""
    inputs(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).touch()
    (out / "database.db").write_bytes(b"not a database\n" * 300)
    done = subprocess.run([sys.executable, "-m", "rigsfm", *RUN], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "400"})
    assert "'out/database.db' is not a database: it is made again" in done.stderr, done.stderr
    assert "internal error" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    with pycolmap.Database.open(out / "database.db") as database:
        assert database.num_images() == 4 and database.num_keypoints() > 0


def test_suggested_commands_keep_a_folder_with_spaces_one_word(tmp_path):
    """A message's suggested command can be pasted into a shell as it is: the folder is shell-quoted."""
    missing = Workspace(tmp_path / "my runs" / "it's here")
    with pytest.raises(WorkspaceError) as error:
        missing.require_result()
    command = str(error.value).split("`")[1]
    assert shlex.split(command)[-1] == str(missing.root)
    assert shlex.split(missing.rerun_hint.split("`")[1])[-2] == str(missing.root)
