"""Folders of files rigsfm writes for other tools (``rigsfm export``, ``rigsfm associate``), which the user may
also keep files in: a manifest in the folder lists every file rigsfm wrote there with its SHA-256, and a later
``--overwrite`` removes or replaces only those still as written (never a file the manifest does not list, nor one
edited since).

- :func:`previous_files` checks a destination before anything is computed: a new or empty folder, or an earlier
  output of the same kind (``--overwrite`` asked), else one line that says what to do;
- :func:`commit` moves the files of a finished temporary folder into it, with their manifest, and removes the
  earlier output's own files that the new one does not write again (its sub-folders once empty).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import stat
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import sha256_file, write_json_atomic

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Previous:
    """An earlier output in a folder, by its manifest: ``ours`` are files still as rigsfm wrote them (their
    checksum matches), ``changed`` listed files that are not (edited, replaced, no checksum, not a plain file),
    ``invalid`` entries that name no file of the folder (absolute, ``..``, a sub-folder): only ``ours`` are ever
    removed."""

    ours: tuple[str, ...] = ()
    changed: tuple[str, ...] = ()
    invalid: tuple[str, ...] = ()


def is_plain_name(name: object, manifest: str) -> bool:
    """A file inside the folder: a relative POSIX path without ``.`` or ``..`` parts, not the manifest itself."""
    return (isinstance(name, str) and name != manifest and "\\" not in name and "\0" not in name
            and not name.startswith("/") and all(part not in ("", ".", "..") for part in name.split("/")))


def files_under(folder: Path) -> list[str]:
    """Every file (and link) below ``folder`` as a relative POSIX path; folders are not entries."""
    names = []
    for here, dirs, files in os.walk(folder):
        for name in [*files, *(d for d in dirs if os.path.islink(os.path.join(here, d)))]:
            names.append(Path(here, name).relative_to(folder).as_posix())
    return sorted(names)


def read_manifest(dest: Path, manifest: str) -> tuple[list[str], dict[str, str], list[str]]:
    """(listed plain names, their recorded SHA-256, entries that are not plain names) of ``dest``'s manifest;
    nothing for a manifest that is missing, a link, or not one rigsfm writes."""
    path = dest / manifest
    if path.is_symlink() or not path.is_file():
        return [], {}, []
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return [], {}, []
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, list):
        return [], {}, []
    sums = data.get("sha256") if isinstance(data.get("sha256"), dict) else {}
    listed = [name for name in files if is_plain_name(name, manifest)]
    invalid = [str(name) for name in files if not is_plain_name(name, manifest)]
    return listed, {name: sums[name] for name in listed if isinstance(sums.get(name), str)}, invalid


def _still_ours(path: Path, checksum: str | None) -> bool:
    """Whether ``path`` is a plain file (not a link) whose content is what rigsfm recorded writing."""
    try:
        if checksum is None or not stat.S_ISREG(os.lstat(path).st_mode):
            return False
        return sha256_file(path) == checksum
    except OSError:
        return False


def previous_files(dest: Path, manifest: str, *, overwrite: bool, option: str, what: str,
                   legacy: Callable[[Path, list[str]], list[str]] | None = None) -> Previous:
    """What an output into ``dest`` may replace: the files of an earlier output listed in ``dest``'s
    ``manifest`` and still as rigsfm wrote them. Refuses a path that is not a folder, a folder with files no
    manifest lists, and an earlier output without ``overwrite``. ``option``: the command's option naming
    ``dest`` (for the messages); ``what``: the output, a noun taking "an" ("export"); ``legacy(dest, present)``: the
    files an earlier version wrote before it kept a manifest, taken as written (recognised by its layout)."""
    if not dest.exists():
        return Previous()
    if not dest.is_dir():
        raise WorkspaceError(f"{option} {dest} exists and is not a folder; choose a new or empty folder")
    present = files_under(dest)
    if not present:
        return Previous()
    listed, sums, invalid = read_manifest(dest, manifest)
    if not listed and legacy is not None:
        listed = legacy(dest, present)
        sums = {name: sha256_file(dest / name) for name in listed if not (dest / name).is_symlink()}
    foreign = [name for name in present if name != manifest and name not in listed]
    nested = sorted({name.split("/")[0] for name in foreign if (dest / name.split("/")[0] / manifest).is_file()})
    if nested:  # rigsfm's, but earlier outputs in folders of their own: name the user's files, if any
        foreign = [name for name in foreign if name.split("/")[0] not in nested]
        if not foreign:
            raise WorkspaceError(f"{option} '{dest}' holds earlier {what}s in folders of their own "
                                 f"({', '.join(n + '/' for n in nested[:3])}{', ...' if len(nested) > 3 else ''}); "
                                 f"give this {what} a folder of its own (nothing was written or removed)")
    if foreign:
        raise WorkspaceError(f"{option} '{dest}' holds files rigsfm did not write ({', '.join(foreign[:3])}"
                             f"{', ...' if len(foreign) > 3 else ''}); choose a new or empty folder (nothing was "
                             "written or removed)")
    if not overwrite:
        raise WorkspaceError(f"{dest} already holds an {what}: pass --overwrite to replace it")
    there = [name for name in listed if os.path.lexists(dest / name)]
    ours = tuple(name for name in there if _still_ours(dest / name, sums.get(name)))
    return Previous(ours, tuple(name for name in there if name not in ours), tuple(invalid))


def refuse_changed(dest: Path, previous: Previous, names: Collection[str], option: str, what: str) -> None:
    """Refuse to write ``names`` where one of them is a listed file no longer as rigsfm wrote it (callable before
    the work, where the names are known then)."""
    collide = [name for name in previous.changed if name in names]
    if collide:
        raise WorkspaceError(f"'{dest / collide[0]}' is not what an earlier {what} wrote there (edited "
                             f"or replaced since); move it away or choose another {option} (nothing was written or "
                             "removed)")


def _replace_previous(dest: Path, previous: Previous, written: list[str], manifest: str, option: str,
                      what: str) -> None:
    """Refuse to write over a listed file that is no longer rigsfm's; remove the earlier output's own files that
    this one does not write again (those it does are replaced by the rename); keep the others with a warning."""
    refuse_changed(dest, previous, written, option, what)
    for name in previous.changed:
        logger.warning("Kept %s: its content is not what rigsfm wrote there (edited or replaced since), so it is no "
                       "longer part of the %s", dest / name, what)
    for name in previous.invalid:
        logger.warning("Ignored %r in %s: not a file of %s, so nothing was removed for it", name, dest / manifest, dest)
    for name in previous.ours:
        if name not in written:
            (dest / name).unlink(missing_ok=True)
            folder = (dest / name).parent
            while folder != dest:  # the output's own sub-folders, once they are empty
                with contextlib.suppress(OSError):
                    folder.rmdir()
                folder = folder.parent


def commit(dest: Path, tmp: Path, previous: Previous, manifest: str, record: dict[str, Any], *,
           option: str, what: str) -> list[str]:
    """Move every file written under ``tmp`` into ``dest`` with ``manifest`` (``record`` plus the files and their
    SHA-256), after removing ``previous``'s own files that are not written again. Returns the files written."""
    written = files_under(tmp)
    write_json_atomic(tmp / manifest, {**record, "files": written,
                                       "sha256": {name: sha256_file(tmp / name) for name in written}})
    dest.mkdir(exist_ok=True)
    _replace_previous(dest, previous, written, manifest, option, what)
    for name in [*written, manifest]:
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / name, dest / name)
    return written
