"""Stage 2, database: the COLMAP database — calibrated cameras, images and the rig configuration with E^sl.

One camera per rig sensor (intrinsics from rigs.yaml, never refined), one image row per file, and one
``pycolmap.Rig`` per rig with the wide camera as reference sensor and ``narrow_from_wide`` as the narrow
sensor's ``sensor_from_rig``. Frames group the wide and narrow images of the same file name.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import sqlite3
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.names import SENSORS
from rigsfm.core.rig import RigCalibration
from rigsfm.run.inputs.images import ImageEntry

logger = logging.getLogger(__name__)


def calibrated_camera(camera: pycolmap.Camera) -> pycolmap.Camera:
    """A copy flagged as calibrated (COLMAP's global mapper trusts only "prior" focal lengths)."""
    copy = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=camera.params)
    copy.has_prior_focal_length = True
    return copy


def rig_configs(rigs: Sequence[RigCalibration], images: Sequence[ImageEntry]) -> list[pycolmap.RigConfig]:
    """COLMAP rig configurations: image prefix ``<rig>/<sensor>/``, wide is the reference sensor.

    COLMAP needs an image of every configured camera, so a rig without narrow images is configured
    with its wide camera alone (its narrow pose still follows from E^sl at export).
    """
    with_narrow = {entry.rig for entry in images if entry.sensor == "narrow"}
    configs = []
    for rig in rigs:
        wide = pycolmap.RigConfigCamera(
            ref_sensor=True, image_prefix=f"{rig.name}/wide/", camera=calibrated_camera(rig.wide)
        )
        if rig.name not in with_narrow:
            configs.append(pycolmap.RigConfig(cameras=[wide]))
            continue
        narrow = pycolmap.RigConfigCamera(
            ref_sensor=False,
            image_prefix=f"{rig.name}/narrow/",
            cam_from_rig=rig.narrow_from_wide,
            camera=calibrated_camera(rig.narrow),
        )
        configs.append(pycolmap.RigConfig(cameras=[wide, narrow]))
    return configs


def _same_camera(a: pycolmap.Camera, b: pycolmap.Camera) -> bool:
    return (
        a.model == b.model
        and (a.width, a.height) == (b.width, b.height)
        and np.allclose(a.params, b.params, rtol=0, atol=1e-12)
    )


def _other_inputs(database: pycolmap.Database, rigs: Sequence[RigCalibration], images: Sequence[ImageEntry]
                  ) -> str | None:
    """How an existing database differs from these images and cameras (it must hold exactly them to be resumed),
    or None."""
    db_images = {image.name: image for image in database.read_all_images()}
    wanted = {entry.name for entry in images}
    if set(db_images) != wanted:
        added, gone = sorted(wanted - set(db_images)), sorted(set(db_images) - wanted)
        which = (f"{added[0]} is in the image folder but not in it" if added
                 else f"{gone[0]} is in it but no longer in the image folder")
        more = len(added) + len(gone) - 1
        return f"was made from other images ({which}{f', and {more} more' if more else ''})"
    cameras = {camera.camera_id: camera for camera in database.read_all_cameras()}
    by_name = {rig.name: rig for rig in rigs}
    for entry in images:
        camera = cameras[db_images[entry.name].camera_id]
        if not _same_camera(camera, by_name[entry.rig].camera(entry.sensor)):
            return f"was made with another calibration for {entry.rig}/{entry.sensor} (rigs.yaml changed)"
    return None


_NEVER_CLOSED: list = []


@contextlib.contextmanager
def open_database(path: Path) -> Iterator[pycolmap.Database]:
    """``pycolmap.Database.open(path)`` as a context, safe on a full disk.

    Closing a database from which entries were deleted runs SQLite's VACUUM, which needs free space. When that
    close fails (disk full), the C++ destructor tries again later, and an exception thrown there aborts the
    whole process (``terminate called ... database or disk is full``, exit 134, after rigsfm's own message). A
    database whose close failed is therefore kept alive until the process ends (the OS closes its file; its
    last transaction is rolled back by SQLite on the next open), and the close's error is raised as usual."""
    database = pycolmap.Database.open(path)
    try:
        yield database
    finally:
        try:
            database.close()
        except RuntimeError:
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(database))  # never destructed: see above
            _NEVER_CLOSED.append(database)
            raise


def damage(path: Path) -> str | None:
    """What is wrong with the database file ``path`` that rebuilding it mends ("is empty", "is not a database",
    "is damaged (...)"), or None (COLMAP's own words for all three are those of a full disk, "No registered
    database factory succeeded"). A sound SQLite database without COLMAP's tables is not rigsfm's: refused."""
    path = Path(path)
    if path.stat().st_size == 0:
        return "is empty"
    try:
        with contextlib.closing(sqlite3.connect(path)) as connection:
            found = [row[0] for row in connection.execute("PRAGMA quick_check")]
            tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.OperationalError:  # locked, unreadable, a full disk: COLMAP's open says which
        return None
    except sqlite3.DatabaseError as error:  # "file is not a database", "database disk image is malformed"
        return "is not a database" if "not a database" in str(error) else f"is damaged ({error})"
    if found != ["ok"]:
        return f"is damaged ({found[0] if found else 'no answer to its check'})"
    if tables and "images" not in tables:
        raise WorkspaceError(f"'{path}' is not a COLMAP database (rigsfm did not write it); choose another --out or "
                             "move it away")
    return None


def check_database_kept(database_path: Path, images: Sequence[ImageEntry]) -> None:
    """Raise a ``WorkspaceError`` when the database no longer holds ``images``: it was removed or replaced while
    this run wrote it (COLMAP's next stage then makes an empty one in its place and fails for want of matches)."""
    database_path = Path(database_path)
    found = None
    if database_path.is_file() and damage(database_path) is None:
        with open_database(database_path) as database:
            found = {image.name for image in database.read_all_images()}
    if found != {entry.name for entry in images}:
        raise WorkspaceError(f"{database_path} was removed or replaced while this run wrote it: re-run the same "
                             "command (the database is made again)")


def create_database(
    database_path: Path, rigs: Sequence[RigCalibration], images: Sequence[ImageEntry], *, overwrite: bool = False
) -> Path:
    """Create the database (or check that an existing one matches these inputs) and return its path; one made from
    other images or calibration is made again with ``overwrite`` (the run replaces its result), else refused."""
    database_path = Path(database_path)
    if database_path.exists():
        problem = damage(database_path)
        if problem is None:
            with open_database(database_path) as database:
                if database.num_images() == 0:
                    problem = "holds no images (removed or replaced while a run wrote it?)"
                else:
                    problem = _other_inputs(database, rigs, images)
                    if problem and not overwrite:  # an unfinished run's: a finished one's is refused earlier
                        raise WorkspaceError(
                            f"'{database_path}' {problem}: pass --overwrite to start again from these inputs, re-run "
                            "with the inputs of the interrupted run to resume it, or choose another --out")
        if problem is None:
            logger.info("Reusing database %s", database_path)
            return database_path
        # Only rigsfm writes this file in its workspace, and what it held is lost anyway: made again in its place.
        logger.warning("'%s' %s: it is made again, and so are its features and matches", database_path, problem)
        for journal in ("-journal", "-wal", "-shm"):  # SQLite's of the old file: never to be applied to the new one
            database_path.with_name(database_path.name + journal).unlink(missing_ok=True)
    tmp_path = database_path.with_name(database_path.name + ".tmp")
    tmp_path.unlink(missing_ok=True)
    with open_database(tmp_path) as database:
        for rig in rigs:
            for sensor in SENSORS:
                camera_id = database.write_camera(calibrated_camera(rig.camera(sensor)))
                for entry in images:
                    if (entry.rig, entry.sensor) == (rig.name, sensor):
                        database.write_image(pycolmap.Image(name=entry.name, camera_id=camera_id))
        pycolmap.apply_rig_config(rig_configs(rigs, images), database)
    tmp_path.replace(database_path)
    logger.info("Created database %s with %d images of %d rigs", database_path, len(images), len(rigs))
    return database_path
