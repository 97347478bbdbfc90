"""The output workspace OUT: one folder whose every path is named here, so any stage can be re-run or resumed.

```
OUT/
  .rigsfm-workspace   marker: this folder was made by rigsfm (--overwrite touches nothing else)
  .rigsfm.lock        held while a command writes OUT (a second one is refused)
  database.db         COLMAP database: cameras, rigs with E^sl, features, verified matches
  features.json       the settings the features and matches were made with
  pairs.txt           the image pairs being matched (transient)
  mapping/            the mapper's raw model (arbitrary units)
  sparse/             the final metric model            narrow_poses.json  points3D.ply  summary.json
  report.html         colmap.log
  export/<format>/    `rigsfm export`                  track/  `rigsfm track` (poses.json, poses.csv, plots/)
```
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import shutil
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rigsfm.core.errors import WorkspaceError

logger = logging.getLogger(__name__)

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
    def track(self) -> TrackPaths:
        return TrackPaths(self.root / "track")

    def export(self, fmt: str) -> Path:
        """The default folder of ``rigsfm export --format fmt``."""
        return self.root / "export" / str(fmt)

    @property
    def results(self) -> tuple[Path, ...]:
        """What a finished run leaves; never replaced without ``overwrite``."""
        return (self.sparse, self.narrow_poses, self.points_ply, self.summary)

    def has_result(self) -> bool:
        return (self.sparse / "images.bin").is_file() and self.narrow_poses.is_file()

    def require_result(self) -> None:
        """Raise a ``WorkspaceError`` saying what to do when OUT holds no finished run."""
        if not self.root.is_dir():
            raise WorkspaceError(f"{self.root} does not exist: run `rigsfm run IMAGES --rigs rigs.yaml --out {self.root}`"
                                 " first")
        if not (self.sparse / "images.bin").is_file():
            raise WorkspaceError(f"{self.root} holds no result ({self.sparse} is missing): run `rigsfm run ... --out "
                                 f"{self.root}` first")
        if not self.narrow_poses.is_file():
            raise WorkspaceError(f"{self.narrow_poses} is missing: re-run `rigsfm run ... --out {self.root} --overwrite`")

    def is_ours(self) -> bool:
        """Whether rigsfm made this folder (its marker, or the files of a run made before the marker existed)."""
        return (self.root / MARKER).is_file() or self.database.is_file() or self.summary.is_file()

    def _check_ours(self) -> None:
        if self.root.exists() and not self.root.is_dir():
            raise WorkspaceError(f"output {self.root} exists and is not a folder; choose another --out")
        if self.root.is_dir() and not self.is_ours() and any(p.name not in (MARKER, LOCK) for p in self.root.iterdir()):
            raise WorkspaceError(f"{self.root} is not empty and was not made by rigsfm; choose a new or empty --out "
                                 "folder (rigsfm never writes among files it did not make)")

    def prepare(self, *, overwrite: bool) -> None:
        """Create the folder; refuse a folder that holds other files, and an existing result unless ``overwrite``.
        A run is finished when its summary.json (written last) exists; what a run stopped while delivering wrote
        before it is replaced, so that the same command resumes."""
        self._check_ours()
        existing = [p.name for p in self.results if p.exists()] if self.summary.exists() else []
        if existing and not overwrite:
            raise WorkspaceError(
                f"{self.root} already holds a result ({', '.join(existing)}); pass --overwrite to replace it "
                "(features and matches made with the same settings are reused) or choose another --out"
            )
        writable(self.root)
        (self.root / MARKER).touch()
        self.sweep()

    def leftovers(self) -> list[Path]:
        """What an interrupted or killed stage left: the temporary files and folders of rigsfm's atomic writes
        (``.<name>.<8 characters>.tmp``, ``.<name>.old``) of this workspace's own files and folders, and
        ``mapping.db`` (and ``.tmp``), the database copy older versions mapped from."""
        if not self.root.is_dir():
            return []
        names = {path.name for path in (self.database, self.feature_settings, self.pairs, self.mapping, *self.results,
                                        self.report)}
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
                raise WorkspaceError(f"{self.root} is in use by process {pid} (another rigsfm command); wait for it to "
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


def writable(folder: Path) -> Path:
    """Create ``folder`` (and parents) and check a file can be written in it; a clear error if not."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".rigsfm-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise WorkspaceError(f"cannot write in {folder}: {os_error_text(error)}; choose a folder you can write to") \
            from None
    return folder


def os_error_text(error: OSError) -> str:
    """The cause of an OS error in words a user acts on (disk full, read-only, permission, ...)."""
    causes = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
              errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
              errno.EPERM: "permission denied", errno.ENOENT: "no such file or folder",
              errno.ENOTDIR: "a part of the path is a file, not a folder", errno.EISDIR: "it is a folder"}
    return causes.get(error.errno, error.strerror or type(error).__name__)


@contextlib.contextmanager
def colmap_log_to(path: Path) -> Iterator[None]:
    """Send COLMAP's log (glog on the process's stderr) and rigsfm's own log records to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path)
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
        sys.stderr.flush()
        os.dup2(saved_fd, 2)
        os.close(saved_fd)
        root_logger.removeHandler(handler)
        root_logger.setLevel(saved_level)
        handler.close()
