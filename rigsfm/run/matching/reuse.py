"""Work already in the database is kept, so an interrupted run resumes where it stopped; work made with other
settings is cleared first (``drop_stale_work``), and so is the work of every image whose file's content is not
what it was made from (``drop_changed_images``: a new recording copied over the same names)."""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
from collections.abc import Sequence
from pathlib import Path

import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.io import file_sha256, write_json_atomic
from rigsfm.core.workspace import os_error_text
from rigsfm.run.inputs.database import open_database
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.matching.extract import work_settings
from rigsfm.run.options import MatchingOptions

logger = logging.getLogger(__name__)


def drop_stale_work(database_path: Path, settings_path: Path, options: MatchingOptions,
                    first_octave: int = -1) -> list[str]:
    """Clear the features and matches a resumed workspace made with other settings than ``options`` (and
    ``first_octave``, :func:`resolved_first_octave`), so a changed option takes effect instead of being silently
    ignored; records the settings. Returns what was cleared (``"features"``, ``"matches"``)."""
    now = work_settings(options, first_octave)
    before = now
    if settings_path.exists():
        try:
            before = json.loads(settings_path.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError):
            logger.warning("%s is unreadable: the features and matches are recomputed", settings_path)
            before = {}
        if not isinstance(before, dict):
            before = {}
    cleared = []
    if before != now:
        with open_database(database_path) as database:
            if before.get("features") != now["features"]:
                database.clear_keypoints()
                database.clear_descriptors()
                cleared.append("features")
            database.clear_matches()
            database.clear_two_view_geometries()
            cleared.append("matches")
        changed = [f"{key}: {before.get(group, {}).get(key)} -> {value}" for group in now
                   for key, value in now[group].items() if before.get(group, {}).get(key) != value]
        logger.warning("Settings changed since this workspace's last run (%s): recomputing its %s",
                       ", ".join(changed), " and ".join(cleared))
    write_json_atomic(settings_path, now)
    return cleared


def image_digests(images: Sequence[ImageEntry]) -> dict[str, str]:
    """Per image name, the SHA-256 of its file (the feature cache's hash, :func:`rigsfm.core.io.file_sha256`)."""
    contents = {}
    for entry in images:
        try:
            contents[entry.name] = file_sha256(entry.path)
        except OSError as error:
            raise InputError(f"cannot read {entry.path}: {os_error_text(error)}; check the image folder") from None
    return contents


def recorded_contents(record_path: Path) -> dict[str, str]:
    """The record :func:`drop_changed_images` wrote ({} when missing or unreadable: nothing is then trusted)."""
    try:
        data = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (ValueError, UnicodeDecodeError):
        logger.warning("%s is unreadable: every image's features and matches are made again", record_path)
        return {}
    contents = data.get("sha256") if isinstance(data, dict) else None
    return {k: v for k, v in contents.items() if isinstance(v, str)} if isinstance(contents, dict) else {}


def drop_changed_images(database_path: Path, record_path: Path, images: Sequence[ImageEntry]) -> list[str]:
    """Clear the features and matches of every image whose file is not the one they were made from (a new
    recording copied over the same names), so that the run works on the images it is given; records each image's
    content (:func:`image_digests`) in ``record_path``. Work in the database for an image the record does not
    name (a workspace of an older rigsfm, a removed record) is cleared too: what it was made from is unknown.
    Unchanged images keep their work. Returns the names whose work was cleared."""
    now = image_digests(images)
    before = recorded_contents(record_path)
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        paired: dict[int, list[int]] = {}  # image id -> the ids it has matches or a two-view geometry with
        for pair_ids in (database.read_num_matches()[0], database.read_two_view_geometry_num_inliers()[0]):
            for pair_id in pair_ids:
                id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
                paired.setdefault(id1, []).append(id2)
                paired.setdefault(id2, []).append(id1)
        stale = [name for name, digest in now.items() if before.get(name) != digest and name in ids
                 and (database.exists_keypoints(ids[name]) or database.exists_descriptors(ids[name])
                      or ids[name] in paired)]
        if stale:
            with pycolmap.DatabaseTransaction(database):
                for name in stale:
                    for other in set(paired.get(ids[name], ())):
                        if database.exists_matches(ids[name], other):
                            database.delete_matches(ids[name], other)
                        if database.exists_two_view_geometry(ids[name], other):
                            database.delete_two_view_geometry(ids[name], other)
    if stale:
        _delete_features(database_path, [ids[name] for name in stale])
        changed = [name for name in stale if name in before]
        unknown = [name for name in stale if name not in before]
        if changed:
            logger.warning("%s changed since the last run in this workspace (%s): %s made again", _count(changed),
                           _names(changed), "its features and matches are" if len(changed) == 1 else
                           "their features and matches are")
        if unknown:
            logger.warning("%s holds no record of what the features and matches of %s were made from (%s): they "
                           "are made again", record_path, _count(unknown), _names(unknown))
    write_json_atomic(record_path, {"sha256": now})
    return stale


def _count(names: Sequence[str]) -> str:
    return f"{len(names)} image{'s' if len(names) != 1 else ''}"


def _names(names: Sequence[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def _delete_features(database_path: Path, image_ids: Sequence[int]) -> None:
    """Remove these images' keypoints and descriptors in one transaction (pycolmap's Database deletes only a
    table's every row; extraction then finds them without features)."""
    rows = [(int(image_id),) for image_id in image_ids]
    try:
        with contextlib.closing(sqlite3.connect(database_path)) as connection, connection:
            connection.executemany("DELETE FROM keypoints WHERE image_id = ?", rows)
            connection.executemany("DELETE FROM descriptors WHERE image_id = ?", rows)
    except sqlite3.OperationalError as error:  # as COLMAP's own errors: a full disk is named by disk_errors_named
        raise RuntimeError(f"{database_path}: {error}") from None
