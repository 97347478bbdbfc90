"""The output workspace OUT: one folder whose every path is named here, so any stage can be re-run or resumed.

```
OUT/
  .rigsfm-workspace   marker: this folder was made by rigsfm (--overwrite touches nothing else)
  .rigsfm.lock        held while a command writes or reads OUT (a second one is refused)
  database.db         COLMAP database: cameras, rigs with E^sl, features, verified matches
  features.json       the settings the features and matches were made with
  images.json         the content (SHA-256) of each image file they were made from
  pairs.txt           the image pairs being matched (transient)
  mapping/            the mapper's raw model (arbitrary units)
  sparse/             the final metric model            narrow_poses.json  points3D.ply  summary.json
  report.html         colmap.log
  export/<format>/    `rigsfm export`                  track/  `rigsfm track` (poses.json, poses.csv, plots/)
  labels.csv          `rigsfm explore`: the analyst's labelled clicks (never removed by rigsfm)
```
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import os
import re
import shlex
import shutil
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rigsfm.core.errors import WorkspaceError

logger = logging.getLogger(__name__)
if TYPE_CHECKING:
    import pycolmap

MARKER = ".rigsfm-workspace"
LOCK = ".rigsfm.lock"


@dataclass(frozen=True)
class TrackPaths:
    """``OUT/track/``: the results of ``rigsfm track``."""

    root: Path

    @property
    def poses_json(self) -> Path:
        return self.root / "poses.json"

    @property
    def poses_csv(self) -> Path:
        return self.root / "poses.csv"

    @property
    def plots(self) -> Path:
        return self.root / "plots"

    def plot(self, rig: str) -> Path:
        return self.plots / f"{rig}.png"


@dataclass(frozen=True)
class Workspace:
    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    @property
    def feature_settings(self) -> Path:
        """The settings the database's features and matches were made with (``features.drop_stale_work``)."""
        return self.root / "features.json"

    @property
    def image_contents(self) -> Path:
        """The SHA-256 of each image file the database's features and matches were made from
        (``features.drop_changed_images``): a new recording under the same names is recognised by its content."""
        return self.root / "images.json"

    @property
    def pairs(self) -> Path:
        """The list of image pairs handed to COLMAP's matcher, one batch at a time."""
        return self.root / "pairs.txt"

    @property
    def mapping(self) -> Path:
        """Wide-camera registration straight out of the mapper (arbitrary units)."""
        return self.root / "mapping"

    @property
    def sparse(self) -> Path:
        """Final metric COLMAP model with rigs, frames, wide and narrow images."""
        return self.root / "sparse"

    @property
    def narrow_poses(self) -> Path:
        return self.root / "narrow_poses.json"

    @property
    def points_ply(self) -> Path:
        return self.root / "points3D.ply"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"

    @property
    def report(self) -> Path:
        return self.root / "report.html"

    @property
    def colmap_log(self) -> Path:
        return self.root / "colmap.log"

    @property
    def labels(self) -> Path:
        """``rigsfm explore``'s labels CSV (the default one)."""
        return self.root / "labels.csv"

    @property
    def track(self) -> TrackPaths:
        return TrackPaths(self.root / "track")

    @property
    def associate(self) -> Path:
        """The default folder of ``rigsfm associate`` (persons per frame)."""
        return self.root / "associate"

    @property
    def exports(self) -> Path:
        """The folder of ``rigsfm export``'s default folders, one per format."""
        return self.root / "export"

    def export(self, fmt: str) -> Path:
        """The default folder of ``rigsfm export --format fmt``."""
        return self.exports / str(fmt)

    def is_within(self, folder: Path) -> bool:
        """Whether the workspace is ``folder`` or lies inside it (a destination there would hold its files)."""
        return self.root.resolve().is_relative_to(Path(folder).resolve())

    def refuse_among_images(self, path: Path, named: str, instead: str) -> None:
        """Refuse to write ``path`` (``named``: the option and path, for the message) inside the image folder of
        the run (summary.json), whose every folder must be a rig: the next `rigsfm run` on it would refuse it."""
        from rigsfm.core.summary import Summary

        summary = Summary.read(self.summary)
        if summary is None or not summary.inputs.images:
            return
        images = Path(summary.inputs.images)
        if Path(path).resolve() == images.resolve() or images.resolve() in Path(path).resolve().parents:
            raise WorkspaceError(f"{named} lies inside the run's image folder {images}, whose every folder must be "
                                 f"a rig (the next `rigsfm run` on it would refuse it); {instead}")

    @property
    def results(self) -> tuple[Path, ...]:
        """What a finished run leaves; never replaced without ``overwrite``."""
        return (self.sparse, self.narrow_poses, self.points_ply, self.summary)

    def has_result(self) -> bool:
        return (self.sparse / "images.bin").is_file() and self.narrow_poses.is_file()

    def require_result(self) -> None:
        """Raise a ``WorkspaceError`` saying what to do when OUT holds no finished run."""
        if self.root.exists() and not self.root.is_dir():  # a file given for OUT (an image, sparse/images.bin, ...)
            raise WorkspaceError(f"'{self.root}' is a file, not the folder of a `rigsfm run` (its --out); give that "
                                 "folder")
        if not self.root.is_dir():
            raise WorkspaceError(f"'{self.root}' does not exist: run `rigsfm run IMAGES --rigs rigs.yaml --out {self.shell_root}`"
                                 " first")
        demo_run = Workspace(self.root / "run")
        if not (self.sparse / "images.bin").is_file() and demo_run.has_result():
            raise WorkspaceError(f"'{self.root}' is a `rigsfm demo` folder, whose result is in its run/ folder: use "
                                 f"{demo_run.root} (e.g. `rigsfm view {demo_run.shell_root}`)")
        if not (self.sparse / "images.bin").is_file() and not self.is_ours() and self._is_image_folder():
            raise WorkspaceError(f"'{self.root}' is an image folder (<rig>/wide/...), not the --out folder of a "
                                 f"`rigsfm run`: give that folder (`rigsfm run {self.shell_root} --rigs rigs.yaml --out "
                                 "OUT` makes one)")
        if not (self.sparse / "images.bin").is_file():
            raise WorkspaceError(f"'{self.root}' holds no result ('{self.sparse}' is missing): run `rigsfm run ... --out "
                                 f"{self.shell_root}` first")
        if not self.narrow_poses.is_file():
            raise WorkspaceError(f"'{self.narrow_poses}' is missing: re-run `rigsfm run ... --out {self.shell_root} --overwrite`")

    def unfinished(self) -> str | None:
        """Why OUT's result is not a finished run's, in a clause, or None: summary.json, which a run writes last,
        is missing (the run stopped while delivering: its files may sit beside an earlier run's)."""
        if self.summary.is_file():
            return None
        return (f"the run that wrote '{self.root}' did not finish (no summary.json, written last; its files may be "
                f"partly an earlier run's): re-run the same `rigsfm run ... --out {self.shell_root}` to finish it")

    def warn_unfinished(self) -> None:
        """One warning line where :meth:`unfinished` says why (``report``, ``export``: read as it is, as ``associate``
        and ``track`` read it)."""
        why = self.unfinished()
        if why is not None:
            logger.warning("%s%s", why[0].upper(), why[1:])

    def _is_image_folder(self) -> bool:
        """Whether the folder looks like IMAGES (a rig folder with a wide/ folder), given where OUT was meant."""
        try:
            return any((rig / "wide").is_dir() for rig in self.root.iterdir() if rig.is_dir())
        except OSError:
            return False

    @property
    def shell_root(self) -> str:
        """The folder as a shell word, for the commands that messages suggest (a space or quote stays one word)."""
        return shlex.quote(str(self.root))

    @property
    def rerun_hint(self) -> str:
        return f"re-run `rigsfm run IMAGES --rigs rigs.yaml --out {self.shell_root} --overwrite`"

    def read_sparse(self) -> pycolmap.Reconstruction:
        """The final model (``sparse/``), or a ``WorkspaceError`` naming the damaged file and the fix."""
        return read_model(self.sparse, self.rerun_hint)

    def read_narrow_poses(self) -> dict:
        return read_json(self.narrow_poses, self.rerun_hint, keys=("narrow", "pairs"))

    def is_ours(self) -> bool:
        """Whether rigsfm made this folder (its marker, or the files of a run made before the marker existed)."""
        return (self.root / MARKER).is_file() or self.database.is_file() or self.summary.is_file()

    def _check_ours(self) -> None:
        if self.root.exists() and not self.root.is_dir():
            raise WorkspaceError(f"output '{self.root}' exists and is not a folder; choose another --out")
        if self.root.is_dir() and not self.is_ours() and any(p.name not in (MARKER, LOCK) for p in self.root.iterdir()):
            raise WorkspaceError(f"'{self.root}' is not empty and was not made by rigsfm; choose a new or empty --out "
                                 "folder (rigsfm never writes among files it did not make)")

    def refuse(self, *, overwrite: bool) -> None:
        """:meth:`prepare`'s refusals alone, nothing made: a folder that holds other files, an existing result
        unless ``overwrite``."""
        self._check_ours()
        existing = [p.name for p in self.results if p.exists()] if self.summary.exists() else []
        if existing and not overwrite:
            raise WorkspaceError(
                f"'{self.root}' already holds a result ({', '.join(existing)}); pass --overwrite to replace it "
                "(features and matches made with the same settings are reused) or choose another --out"
            )

    def prepare(self, *, overwrite: bool) -> None:
        """Create the folder; refuse a folder that holds other files, and an existing result unless ``overwrite``.
        A run is finished when its summary.json (written last) exists; what a run stopped while delivering wrote
        before it is replaced, so that the same command resumes."""
        self.refuse(overwrite=overwrite)
        writable(self.root)
        (self.root / MARKER).touch()
        self.sweep()

    def leftovers(self) -> list[Path]:
        """What an interrupted or killed stage left: the temporary files and folders of rigsfm's atomic writes
        (``.<name>.<8 characters>.tmp``, ``.<name>.old``) of this workspace's own files and folders, and
        ``mapping.db`` (and ``.tmp``), the database copy older versions mapped from."""
        if not self.root.is_dir():
            return []
        names = {path.name for path in (self.database, self.feature_settings, self.image_contents, self.pairs,
                                        self.mapping, *self.results, self.report)}
        pattern = re.compile(r"\.(?P<name>.+)\.(?:[a-z0-9_]{8}\.tmp|old)")
        found = []
        for path in self.root.iterdir():
            match = pattern.fullmatch(path.name)
            if (match and match["name"] in names) or path.name in ("mapping.db", "mapping.db.tmp"):
                found.append(path)
        return sorted(found)

    def sweep(self) -> list[Path]:
        """Remove :meth:`leftovers` (only ever names rigsfm writes); returns what was removed."""
        removed = self.leftovers()
        for path in removed:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        if removed:
            logger.info("Removed what an interrupted run left in %s: %s", self.root, ", ".join(p.name for p in removed))
        return removed

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold OUT for one command: a second command on the same OUT is refused with the first one's PID."""
        self._check_ours()
        writable(self.root)
        path = self.root / LOCK
        with open(path, "a+") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.seek(0)
                pid = handle.read().strip() or "?"
                raise WorkspaceError(f"'{self.root}' is in use by process {pid} (another rigsfm command); wait for it to "
                                     "finish or choose another --out") from None
            handle.seek(0)
            handle.truncate()
            handle.write(str(os.getpid()))
            handle.flush()
            try:
                yield
            finally:
                handle.seek(0)
                handle.truncate()
                fcntl.flock(handle, fcntl.LOCK_UN)

    @contextlib.contextmanager
    def reading(self) -> Iterator[None]:
        """:meth:`lock` for a command that reads OUT's result (``export``, ``associate``): a run rewriting the model
        under it is refused, as it is under ``report``. Held where rigsfm can hold it: a result copied without
        rigsfm's marks, or an OUT this process cannot write (where no rigsfm command of its own writes either), is
        read without it. Call :meth:`require_result` first (the lock makes a missing folder)."""
        if not self.is_ours() or _write_probe(self.root) is not None:
            yield
            return
        with self.lock():
            yield


def model_fingerprint(sparse: Path) -> str:
    """SHA-256 over the model files: what `rigsfm track` and `associate` made from a model (poses.json, persons) is
    only comparable against the same model, not one a later `rigsfm run --overwrite` wrote."""
    digest = hashlib.sha256()
    for path in sorted(Path(sparse).iterdir()):
        if path.is_file():
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")  # rigs.bin and frames.bin: COLMAP 4 models only


def read_model(folder: Path, fix: str) -> pycolmap.Reconstruction:
    """``pycolmap.Reconstruction(folder)``, with a ``WorkspaceError`` naming the folder, what is wrong and ``fix``
    instead of COLMAP's words (a truncated images.bin says "vector::reserve", a missing one "Check failed")."""
    import pycolmap

    folder = Path(folder)
    missing = [name for name in MODEL_FILES if not (folder / name).is_file()]
    empty = [name for name in MODEL_FILES if name not in missing and (folder / name).stat().st_size == 0]
    if missing or empty:
        what = "; ".join(filter(None, [missing and f"{', '.join(missing)} missing",  # type: ignore[list-item]
                                       empty and f"{', '.join(empty)} empty"]))  # type: ignore[list-item]
        raise WorkspaceError(f"'{folder}' holds no complete COLMAP model ({what}): {fix}")
    from rigsfm.core.model_files import ModelFileError, check_model_files

    try:
        check_model_files(folder)  # pycolmap allocates whatever a damaged count says, for minutes
    except ModelFileError as error:
        raise WorkspaceError(f"'{error.path}' is truncated or damaged ({error.what}): {fix}") from None
    except OSError as error:
        raise WorkspaceError(f"cannot read the COLMAP model in '{folder}': {os_error_text(error)}: {fix}") from None
    try:
        return pycolmap.Reconstruction(str(folder))
    except Exception as error:  # ValueError, IndexError ("unordered_map::at"), MemoryError, ... by where it is cut
        cause = re.sub(r"^\[[\w.]+:\d+\]\s*", "", (str(error).splitlines() or [""])[0].strip())
        cause = cause or type(error).__name__
        sizes = ", ".join(f"{p.name} {p.stat().st_size} B" for p in sorted(folder.glob("*.bin")))
        raise WorkspaceError(f"{folder}: the COLMAP model cannot be read ({cause}; a file is truncated or damaged: "
                             f"{sizes}): {fix}") from None


def read_json(path: Path, fix: str, *, keys: tuple[str, ...] = ()) -> Any:
    """A JSON file rigsfm wrote; a ``WorkspaceError`` naming it and ``fix`` when it is missing, not JSON, or lacks
    one of ``keys`` at its top level (a file cut short by a full disk, or edited by hand)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise WorkspaceError(f"'{path}' is missing: {fix}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise WorkspaceError(f"'{path}' is not valid JSON ({error}): {fix}") from None
    if keys and (not isinstance(data, dict) or any(key not in data for key in keys)):
        lacking = [k for k in keys if not isinstance(data, dict) or k not in data]
        raise WorkspaceError(f"'{path}' is not a file rigsfm wrote (no {', '.join(lacking)}): {fix}")
    return data


def _write_probe(folder: Path) -> str | None:
    """Create ``folder`` (and parents) and a file in it; why that fails (``os_error_text``), or None."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".rigsfm-write-test-", dir=folder)  # a new file: never one of the user's
        os.close(fd)
        Path(probe).unlink()
    except OSError as error:
        return os_error_text(error)
    return None


def writable(folder: Path) -> Path:
    """Create ``folder`` (and parents) and check a file can be written in it; a clear error if not."""
    folder = Path(folder)
    problem = _write_probe(folder)
    if problem is not None:
        raise WorkspaceError(f"cannot write in '{folder}': {problem}; choose a folder you can write to")
    return folder


MIN_FREE_BYTES = 1 << 20  # less free space than this and a failed write is put down to a full disk


def disk_problem(folder: Path) -> str | None:
    """Why files cannot be written in ``folder`` now (the disk is full, read-only, permission denied), or None."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        stats = os.statvfs(folder)
        if stats.f_bavail * stats.f_frsize < MIN_FREE_BYTES:
            return f"the disk is full ({stats.f_bavail * stats.f_frsize / 1024:.0f} kB free)"
    except OSError:
        pass
    return _write_probe(folder)


@contextlib.contextmanager
def disk_errors_named(folder: Path) -> Iterator[None]:
    """Turn a failure that comes from the disk under ``folder`` into one line naming it and the cause. COLMAP's
    words do not say it: "No registered database factory succeeded" (SQLite cannot open the database on a full
    disk), an OSError without a file name, a truncated write. Other errors pass unchanged."""
    try:
        yield
    except (RuntimeError, ValueError, OSError) as error:
        problem = disk_problem(folder)
        if problem is None:
            raise
        cause = (str(error).splitlines() or [""])[0].strip() or type(error).__name__
        raise WorkspaceError(f"cannot write in '{folder}': {problem} ({cause}); free space or choose another --out, "
                             "then re-run the same command (finished work is kept)") from None


def os_error_text(error: OSError) -> str:
    """The cause of an OS error in words a user acts on (disk full, read-only, permission, ...)."""
    causes = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
              errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
              errno.EPERM: "permission denied", errno.ENOENT: "no such file or folder",
              errno.ENOTDIR: "a part of the path is a file, not a folder", errno.EISDIR: "it is a folder"}
    return causes.get(error.errno, error.strerror or type(error).__name__)  # type: ignore[arg-type]  # None: not found


class _LogFileHandler(logging.FileHandler):
    """colmap.log's handler: a record it cannot write (a full disk) is dropped; the error itself reaches the user
    as rigsfm's one line, not as logging's report on stderr."""

    def handleError(self, record: logging.LogRecord) -> None:
        pass


@contextlib.contextmanager
def colmap_log_to(path: Path) -> Iterator[None]:
    """Send COLMAP's log (glog on the process's stderr) and rigsfm's own log records to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = _LogFileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root_logger = logging.getLogger("rigsfm")
    saved_level = root_logger.level
    root_logger.setLevel(logging.INFO)
    root_logger.addHandler(handler)
    sys.stderr.flush()
    saved_fd = os.dup(2)
    with open(path, "a") as log_file:
        os.dup2(log_file.fileno(), 2)
    try:
        yield
    finally:
        try:
            sys.stderr.flush()
        except OSError:  # the log's disk is full: what Python held for it is lost, the terminal's stderr is not
            pass
        os.dup2(saved_fd, 2)
        os.close(saved_fd)
        root_logger.removeHandler(handler)
        root_logger.setLevel(saved_level)
        handler.close()
