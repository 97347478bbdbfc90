"""The labels CSV: one labelled click per row, ``image,x,y,person`` (header written), COLMAP pixels of the raw narrow
image, a person label that is not a number (so a reader of ``image, x, y[, score][, label]`` takes it as the label).

Rows that are not labels of this OUT's narrow images (another format, an image the model does not hold, a pixel
outside the image) are *foreign*: they are kept, in their place at the end of the file, with a warning, and the file
as it was is copied to a backup before rigsfm first rewrites it.

A click belongs to the picture it was made on, not to a file name: ``<CSV>.images.json`` records each labelled
image's SHA-256 when its labels are saved. Labels whose image has changed since (a new recording under the same
names, a `rigsfm run --overwrite` on it) are *stale*: not shown or checked, with a warning, and left out of the CSV
at the next save, after the file as it was is copied to a backup. Labels of an image the record does not name (a CSV
written by hand or before the record) are taken as they are.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

from rigsfm.core.errors import InputError
from rigsfm.core.io import (
    file_sha256,
    read_user_text,
    write_bytes_atomic,
    write_json_atomic,
    write_text_atomic,
)

logger = logging.getLogger(__name__)

HEADER = ["image", "x", "y", "person"]


@dataclass(frozen=True)
class Label:
    image: str
    x: float
    y: float
    person: str

    def cells(self) -> list[str]:
        return [self.image, f"{self.x:.3f}", f"{self.y:.3f}", self.person]


@dataclass(frozen=True)
class ForeignRow:
    line: int
    cells: list[str]
    why: str


def is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def person_problem(person) -> str | None:
    """Why a person label cannot be used, or None."""
    if not isinstance(person, str) or not person.strip():
        return "the person label is empty"
    if person != person.strip() or any(c in person for c in ",\"\r\n"):
        return f"person {person!r} has spaces at its ends, a comma, a quote or a line break"
    if is_number(person):
        return f"person {person!r} is a number (a DETECTIONS reader would take it for a score); use e.g. p{person}"
    return None


def parse_row(cells: list[str], sizes: dict[str, tuple[int, int]]) -> tuple[Label | None, str]:
    """A label from the cells of one row, or None and why not (``sizes``: image name -> (width, height))."""
    cells = [c.strip() for c in cells]
    if len(cells) != 4:
        return None, f"{len(cells)} columns, not 4 (image,x,y,person)"
    image, x, y, person = cells
    if image not in sizes:
        return None, f"{image!r} is not a narrow image of this result"
    try:
        xf, yf = float(x), float(y)
    except ValueError:
        return None, f"x, y ({x!r}, {y!r}) are not numbers"
    width, height = sizes[image]
    if not (math.isfinite(xf) and math.isfinite(yf) and 0 <= xf <= width and 0 <= yf <= height):
        return None, f"({x}, {y}) lies outside {image} ({width}x{height})"
    problem = person_problem(person)
    if problem is not None:
        return None, problem
    return Label(image, xf, yf, person), ""


def read_labels(path: Path, sizes: dict[str, tuple[int, int]]) -> tuple[list[Label], list[ForeignRow]]:
    """The labels of a CSV and its foreign rows (module docstring); a missing file holds none."""
    path = Path(path)
    if not path.exists():
        return [], []
    text = read_user_text(path, "labels")
    labels, foreign = [], []
    for number, cells in enumerate(csv.reader(io.StringIO(text)), start=1):
        if not cells or not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if [c.strip().lower() for c in cells] == HEADER:
            continue
        label, why = parse_row(cells, sizes)
        if label is None:
            foreign.append(ForeignRow(number, cells, why))
        else:
            labels.append(label)
    if foreign:
        first = foreign[0]
        logger.warning("FOREIGN ROWS: %s: %d foreign row%s (not a label of this result's narrow images) kept as %s "
                       "and not used (line %d: %s)", path, len(foreign), "" if len(foreign) == 1 else "s",
                       "it is" if len(foreign) == 1 else "they are", first.line, first.why)
    return labels, foreign


def format_labels(labels: list[Label], foreign: list[ForeignRow]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(HEADER)
    for label in labels:
        writer.writerow(label.cells())
    for row in foreign:
        writer.writerow(row.cells)
    return buffer.getvalue()


def backup_path(path: Path) -> Path:
    """``<CSV>.bak``, or the first ``<CSV>.bak<N>`` not taken by an older, different backup."""
    path = Path(path)
    data = path.read_bytes() if path.is_file() else b""
    for k in range(1, 1000):
        candidate = path.with_name(path.name + (".bak" if k == 1 else f".bak{k}"))
        if not candidate.exists() or candidate.read_bytes() == data:
            return candidate
    raise InputError(f"{path}: 999 backups exist next to it; move them away")


def save_labels(path: Path, labels: list[Label], foreign: list[ForeignRow], *, backup: bool) -> Path | None:
    """Write the CSV atomically; with ``backup``, copy the file as it was to :func:`backup_path` first. Returns
    the backup written, if any."""
    path = Path(path)
    written = None
    if backup and path.is_file():
        written = write_bytes_atomic(backup_path(path), path.read_bytes())
        logger.warning("%s as it was is kept in %s", path, written)
    write_text_atomic(path, format_labels(labels, foreign))
    return written


def record_path(path: Path) -> Path:
    """``<CSV>.images.json``: the image each saved label was clicked on (module docstring)."""
    path = Path(path)
    return path.with_name(path.name + ".images.json")


class ImageDigests:
    """SHA-256 of image files, each read again only when its size or time changed."""

    def __init__(self, images_dir: Path | None):
        self.images_dir = Path(images_dir) if images_dir is not None else None
        self._known: dict[str, tuple[tuple[int, int], str]] = {}

    def __call__(self, name: str) -> str | None:
        """The image's digest, or None where it cannot be read (no folder, no file)."""
        if self.images_dir is None:
            return None
        path = self.images_dir / name
        try:
            stat = path.stat()
            key = (stat.st_size, stat.st_mtime_ns)
            if name not in self._known or self._known[name][0] != key:
                self._known[name] = (key, file_sha256(path))
        except OSError:
            return None
        return self._known[name][1]


def read_record(path: Path) -> dict[str, str]:
    """The recorded digest per image of the labels CSV ``path``; none where there is no readable record."""
    try:
        images = json.loads(record_path(path).read_text(encoding="utf-8")).get("images")
    except (OSError, ValueError, AttributeError):
        return {}
    return {str(k): v for k, v in images.items() if isinstance(v, str)} if isinstance(images, dict) else {}


def drop_stale(path: Path, labels: list[Label], digests: ImageDigests) -> tuple[list[Label], list[Label]]:
    """The labels still on the pictures they were clicked on, and the stale ones (module docstring), with a warning
    naming the latter's images."""
    record = read_record(path)
    fresh: list[Label] = []
    stale: list[Label] = []
    for label in labels:
        now = digests(label.image) if label.image in record else None
        (stale if now is not None and now != record[label.image] else fresh).append(label)
    if stale:
        images = sorted({label.image for label in stale})
        logger.warning("STALE LABELS: %s: %d label(s) on %d image(s) (%s%s) were clicked on other pictures of the same "
                       "name (the files changed since); they are not shown or checked, and the next save leaves them "
                       "out after keeping the CSV as it is in a backup", path, len(stale), len(images),
                       ", ".join(images[:3]), " ..." if len(images) > 3 else "")
    return fresh, stale


def save_record(path: Path, labels: list[Label], digests: ImageDigests) -> None:
    """Record the digest of every image ``labels`` holds, as the CSV ``path`` is saved with them."""
    images = {}
    for name in sorted({label.image for label in labels}):
        digest = digests(name)
        if digest is not None:
            images[name] = digest
    write_json_atomic(record_path(path), {
        "about": "the SHA-256 of each labelled image when its labels were saved (as the run's images.json): rigsfm "
                 "explore sets aside labels whose image has changed since", "images": images})
