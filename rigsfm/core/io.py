"""Atomic writes and small file-format helpers shared by every stage."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

from rigsfm.core.errors import InputError, WorkspaceError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _check_overwrite(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise WorkspaceError(f"{path} already exists: pass --overwrite to replace it")


def write_bytes_atomic(path: Path, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to a temporary file beside ``path``, then rename it into place."""
    path = Path(path)
    _check_overwrite(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as error:
        Path(tmp).unlink(missing_ok=True)
        if error.filename is None:  # a full disk fails the write itself, which names no file
            raise OSError(error.errno, error.strerror, str(path)) from None
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def sha256_file(path: Path) -> str:
    """The SHA-256 of a file's content (hex): what a manifest records so that a later command removes a file only
    while it is still what rigsfm wrote."""
    import hashlib

    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def write_npz_atomic(path: Path, arrays: dict[str, Any], *, overwrite: bool = True) -> Path:
    """``numpy.savez`` of ``arrays`` written atomically (whole or absent for a process reading meanwhile)."""
    import numpy as np

    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return write_bytes_atomic(path, buffer.getvalue(), overwrite=overwrite)


def read_npz(path: Path) -> dict[str, Any] | None:
    """The arrays of an ``.npz`` file, or None when it is missing or unreadable (truncated, not an npz): for
    caches, whose entries are made again then."""
    import numpy as np

    try:
        with np.load(path) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None


def write_text_atomic(path: Path, text: str, *, overwrite: bool = True) -> Path:
    """Write ``text`` (UTF-8) to a temporary file beside ``path``, then rename it into place."""
    return write_bytes_atomic(path, text.encode("utf-8"), overwrite=overwrite)


def write_json_atomic(path: Path, data: Any, *, overwrite: bool = True) -> Path:
    return write_text_atomic(path, json.dumps(data, indent=2) + "\n", overwrite=overwrite)


def _foreign_entries(old: Path, new: Path) -> list[str]:
    """What in ``old`` the folder ``new`` does not write again as a plain file: not rigsfm's to remove."""
    names = {p.name for p in new.iterdir()}
    return sorted(p.name for p in old.iterdir() if p.name not in names or p.is_symlink() or not p.is_file())


@contextlib.contextmanager
def atomic_directory(path: Path, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary directory that replaces ``path`` only if the block succeeds. The folder it replaces may
    hold only plain files of the names the new one holds (an earlier version of it); anything else there (a
    sub-folder, a link, a file of another name) is refused with nothing replaced."""
    path = Path(path)
    _check_overwrite(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
    try:
        yield tmp
        if path.is_symlink() or (path.exists() and not path.is_dir()):
            raise WorkspaceError(f"{path} exists and is not a folder rigsfm wrote; move it away (nothing was replaced)")
        foreign = _foreign_entries(path, tmp) if path.exists() else []
        if foreign:
            raise WorkspaceError(f"{path} holds files rigsfm did not write there ({', '.join(foreign[:3])}"
                                 f"{', ...' if len(foreign) > 3 else ''}); move them away (nothing was replaced)")
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


BOMS = ((b"\xef\xbb\xbf", "utf-8-sig"), (b"\xff\xfe", "utf-16"), (b"\xfe\xff", "utf-16"))


def read_user_text(path: Path, what: str) -> str:
    """A text file a user made: UTF-8, with or without the byte-order mark spreadsheets and Windows editors write,
    or UTF-16 with its mark ("Unicode text" in Excel); anything else is refused naming the file and the fix."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} file {path} does not exist")
    try:
        data = path.read_bytes()
    except OSError as error:
        from rigsfm.core.workspace import os_error_text

        raise InputError(f"cannot read {what} file {path}: {os_error_text(error)}") from None
    encoding = next((name for bom, name in BOMS if data.startswith(bom)), "utf-8")
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not {encoding.upper()} text (byte {e.start}); save it as UTF-8 (e.g. 'CSV UTF-8' "
                         "in a spreadsheet)") from None


# libyaml's parser where PyYAML was built with it (its wheels are): the same documents, ~9x faster than the pure-Python
# one (a rigs.yaml with sigmas: 1.6 against 13.7 ms), which the fuzz tests' thousands of files felt.
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` with libyaml's parser where available (raises ``yaml.YAMLError`` alike)."""
    return yaml.load(text, Loader=_SAFE_LOADER)  # noqa: S506  (a safe loader)


def load_yaml_or_json(path: Path, what: str) -> Any:
    """Parse a YAML (or JSON, a subset of YAML) file, with an error that names the file."""
    path = Path(path)
    text = read_user_text(path, what)
    try:
        data = parse_yaml(text)
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be a {what} file; fix the syntax") from None
    except yaml.YAMLError as e:
        first_line = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{path}: not valid YAML/JSON ({first_line}); fix the syntax") from e
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping at the top level of the {what} file")
    return data
