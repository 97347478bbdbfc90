"""The output workspace: one folder, fixed artifact names, so any stage can be re-run or resumed."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rigsfm.core.errors import WorkspaceError


@dataclass(frozen=True)
class Workspace:
    root: Path

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    @property
    def feature_settings(self) -> Path:
        """The settings the database's features and matches were made with (``features.drop_stale_work``)."""
        return self.root / "features.json"

    @property
    def mapping(self) -> Path:
        """Wide-camera registration straight out of the mapper (arbitrary units)."""
        return self.root / "mapping"

    @property
    def mapping_database(self) -> Path:
        """The database copy the mapper reads (see ``mapping.mapping_database``)."""
        return self.root / "mapping.db"

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
    def colmap_log(self) -> Path:
        return self.root / "colmap.log"

    @property
    def results(self) -> tuple[Path, ...]:
        """What a finished run leaves; never replaced without ``overwrite``."""
        return (self.sparse, self.narrow_poses, self.points_ply, self.summary)

    def prepare(self, *, overwrite: bool) -> None:
        """Create the folder; refuse to touch an existing result unless ``overwrite``."""
        if self.root.exists() and not self.root.is_dir():
            raise WorkspaceError(f"output {self.root} exists and is not a folder")
        existing = [p.name for p in self.results if p.exists()]
        if existing and not overwrite:
            raise WorkspaceError(
                f"{self.root} already holds a result ({', '.join(existing)}); "
                "pass --overwrite to replace it (features and matches made with the same settings are reused) or choose another --out"
            )
        self.root.mkdir(parents=True, exist_ok=True)


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
