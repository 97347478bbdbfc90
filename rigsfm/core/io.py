"""Atomic writes and small file-format helpers shared by every stage."""

from __future__ import annotations

import contextlib
import errno
import gc
import hashlib
import io
import json
import os
import re
import shutil
import stat
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
        # a full disk fails the write itself, which names no file; a failed rename names the temporary file, which
        # the user never made: both are the user's path
        if error.filename is None or str(error.filename) == str(tmp):
            raise OSError(error.errno, error.strerror, str(path)) from None
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# the temporary names write_bytes_atomic and atomic_directory make beside a path: '.NAME.' + tempfile's 8 characters
# + '.tmp'
_TEMPORARY_NAME = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp$")


def real_path(path: str | os.PathLike) -> str:
    """``path`` with each temporary name rigsfm writes under (``.NAME.x1y2z3w4.tmp``) replaced by the NAME it
    becomes: what a message names, as the user never made the temporary file or folder."""
    parts = str(path).split(os.sep)
    return os.sep.join(match.group("name") if (match := _TEMPORARY_NAME.match(part)) else part for part in parts)


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
            raise WorkspaceError(f"'{path}' exists and is not a folder rigsfm wrote; move it away (nothing was replaced)")
        foreign = _foreign_entries(path, tmp) if path.exists() else []
        if foreign:
            raise WorkspaceError(f"'{path}' holds files rigsfm did not write there ({', '.join(foreign[:3])}"
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


def file_sha256(path: Path, prefix: bytes = b"") -> str:
    """SHA-256 (hex) of ``prefix`` followed by the file's bytes: what an image's features are recognised by (the
    feature cache's key, the workspace's record of each input image), read in chunks so a large image costs no
    second copy in memory."""
    digest = hashlib.sha256(prefix)
    with open(path, "rb") as file:
        for chunk in iter(lambda: file.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


BOMS = ((b"\xef\xbb\xbf", "utf-8-sig"), (b"\xff\xfe", "utf-16"), (b"\xfe\xff", "utf-16"))


def file_kind(mode: int) -> str | None:
    """What a non-regular file is, in words (None for a regular file)."""
    for test, words in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                        (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return words
    return None if stat.S_ISREG(mode) else "not a regular file"


def access_problem(path: Path, error: OSError) -> str:
    """Why ``path`` cannot be opened, with the fix (the true cause: a missing file, a broken link, a link loop,
    a permission), for a message that starts with the path."""
    if error.errno == errno.ELOOP:
        return "is a symbolic link loop (it points, through links, back at itself); point it at the real file"
    if error.errno == errno.ENOENT:
        if os.path.islink(path):
            return f"is a symbolic link to {os.readlink(path)}, which does not exist; point it at the real file"
        return "does not exist; check the path"
    if error.errno in (errno.EACCES, errno.EPERM):
        return ("cannot be read: permission denied (on it or a folder above it); give yourself read permission "
                "(chmod u+r, and u+x on the folders) or copy it somewhere you can read")
    if error.errno == errno.ENOTDIR:
        return "does not exist: a part of its path is a file, not a folder; check the path"
    return f"cannot be read ({error.strerror or type(error).__name__}); check the path"


def stat_input(path: Path, label: str) -> tuple[os.stat_result, str | None]:
    """``path``'s status (following links) and :func:`file_kind` of it; an ``InputError`` starting with ``label``
    and the path, with the true cause and the fix, when it cannot be read."""
    try:
        info = os.stat(path)
    except OSError as error:
        raise InputError(f"{label} '{path}' {access_problem(path, error)}") from None
    return info, file_kind(info.st_mode)


def check_regular_file(path: Path, what: str) -> os.stat_result:
    """``path`` is a regular file rigsfm can open (following links); an ``InputError`` with the true cause and the
    fix otherwise: a folder, FIFO or device is no ``what`` file (and a FIFO would block the read forever)."""
    path = Path(path)
    info, kind = stat_input(path, f"{what} file")
    if kind is not None:
        raise InputError(f"{what} file '{path}' is {kind}, not a regular file; give the path of the {what} file itself")
    return info


def read_user_text(path: Path, what: str, *, max_bytes: int | None = None) -> str:
    """A text file a user made: UTF-8, with or without the byte-order mark spreadsheets and Windows editors write,
    or UTF-16 with its mark ("Unicode text" in Excel); anything else is refused naming the file and the fix.
    A file over ``max_bytes`` is refused before it is read (no such file is a real one: a wrong file)."""
    path = Path(path)
    info = check_regular_file(path, what)
    if max_bytes is not None and info.st_size > max_bytes:
        raise InputError(f"{what} file '{path}' is {info.st_size / 2**20:.1f} MiB, over the {max_bytes / 2**20:g} MiB any "
                         "real one takes; is it the right file?")
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(f"{what} file '{path}' {access_problem(path, error)}") from None
    encoding = next((name for bom, name in BOMS if data.startswith(bom)), "utf-8")
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not {encoding.upper()} text (byte {e.start}); save it as UTF-8 (e.g. 'CSV UTF-8' "
                         "in a spreadsheet)") from None


# libyaml's parser where PyYAML was built with it (its wheels are): the same documents, far faster than the
# pure-Python one, which the fuzz tests' thousands of files feel.
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping gives one key twice (YAML and JSON parsers otherwise keep the last silently)."""


class NumberTooLongError(yaml.constructor.ConstructorError):
    """A whole number of more digits than Python converts (4300 by default), which no rigsfm value needs."""


class _UniqueKeyLoader(_SAFE_LOADER):  # type: ignore[valid-type,misc]  # a base chosen at import
    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._tags: dict[str, str] = {}

    def resolve(self, kind, value, implicit):
        # a plain scalar's tag depends on its text alone (SafeLoader has no path resolvers): rigs.yaml repeats its
        # keys and many of its numbers in every rig, and each resolution runs the regular expressions in Python
        if kind is yaml.ScalarNode and implicit[0]:
            tag = self._tags.get(value)
            if tag is None:
                tag = self._tags[value] = super().resolve(kind, value, implicit)
            return tag
        return super().resolve(kind, value, implicit)

    # SafeLoader has no path resolvers, for which the composer tells each node's place (a Python call per node)
    def descend_resolver(self, current_node, current_index):
        pass

    def ascend_resolver(self):
        pass

    def construct_yaml_int(self, node):
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # Python's limit on the digits it converts, which PyYAML does not expect
            digits = sum(c.isdigit() for c in node.value)
            raise NumberTooLongError(None, None, f"a whole number of {digits} digits is beyond any value here; give "
                                     "the number it stands for", node.start_mark) from None

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *anchor' may be overridden by design
                    continue
                # a plain string key is itself (cheap: rigs.yaml has thousands); others as constructed
                key = key_node.value if key_node.tag == "tag:yaml.org,2002:str" \
                    else self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:  # an unhashable key: SafeConstructor refuses it with its own message
                    continue
                if first is not key_node:
                    raise _duplicate(key, first, key_node)
        return super().construct_mapping(node, deep=deep)


def _duplicate(key: Any, first: yaml.Node, again: yaml.Node) -> DuplicateKeyError:
    return DuplicateKeyError(None, None, f"the key {key!r} is given twice (first on line {first.start_mark.line + 1}), "
                             "and only one can count; keep one", again.start_mark)


class _NotPlainData(Exception):
    """A node the plain-data builder leaves to PyYAML's constructor (other tags, merge keys, cycles, odd keys)."""


_TAG = "tag:yaml.org,2002:"


def _plain_data(loader: Any, root: yaml.Node) -> Any:
    """What SafeLoader constructs from ``root``, for documents of mappings, sequences, strings, numbers, booleans
    and nulls (every rigsfm file), built in one walk: PyYAML's general constructor spends ~10 us a node on its
    bookkeeping (a 1 000-rig rigs.yaml has 136 000). Keys given twice raise :class:`DuplicateKeyError`, a mapping's
    keys checked before its values as the constructor does; anything else raises :class:`_NotPlainData`."""
    built: dict[int, Any] = {}  # an anchored node is one object wherever it is referenced, as PyYAML makes it
    active: set[int] = set()
    bools = loader.bool_values

    def build(node: yaml.Node) -> Any:
        tag = node.tag
        if type(node) is yaml.ScalarNode:
            value = node.value
            if tag == _TAG + "str":
                return value
            if tag == _TAG + "float":
                try:
                    return float(value)  # underscores read alike; '.inf', '1:30.5' and the like fail here
                except ValueError:
                    return loader.construct_yaml_float(node)
            if tag == _TAG + "int":
                digits = value.lstrip("+-")
                if digits[:1] != "0" or digits == "0":  # a leading zero is octal, 0x hexadecimal, 0b binary
                    with contextlib.suppress(ValueError):  # '1:30' (base 60)
                        return int(value)
                return loader.construct_yaml_int(node)
            if tag == _TAG + "bool":
                return bools[value.lower()]
            if tag == _TAG + "null":
                return None
            raise _NotPlainData
        ident = id(node)
        if ident in built:
            return built[ident]
        if ident in active:
            raise _NotPlainData
        active.add(ident)
        if type(node) is yaml.SequenceNode and tag == _TAG + "seq":
            result: Any = [build(child) for child in node.value]
        elif type(node) is yaml.MappingNode and tag == _TAG + "map":
            pairs = node.value
            if any(key_node.tag == _TAG + "merge" for key_node, _ in pairs):
                raise _NotPlainData
            keys = [build(key_node) for key_node, _ in pairs]
            try:
                result = dict.fromkeys(keys)
            except TypeError:  # an unhashable key: PyYAML's constructor refuses it with its own message
                raise _NotPlainData from None
            if len(result) < len(keys):
                firsts: dict = {}
                for key, (key_node, _) in zip(keys, pairs, strict=True):
                    first = firsts.setdefault(key, key_node)
                    if first is not key_node:
                        raise _duplicate(key, first, key_node)
            for key, (_, value_node) in zip(keys, pairs, strict=True):
                result[key] = build(value_node)
        else:
            raise _NotPlainData
        active.discard(ident)
        built[ident] = result
        return result

    return build(root)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` with libyaml's parser where available (raises ``yaml.YAMLError`` alike), refusing a key
    given twice in one mapping (:class:`DuplicateKeyError`)."""
    loader = _UniqueKeyLoader(text)
    collecting = gc.isenabled()
    # the cyclic collector would walk every node built so far again and again (two thirds of the time on a 1 000-rig
    # file); a node tree holds no cycles of its own, so nothing is left for it to collect afterwards
    gc.disable()
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        try:
            return _plain_data(loader, root)
        except _NotPlainData:
            return loader.construct_document(root)
    finally:
        if collecting:
            gc.enable()
        loader.dispose()


def yaml_error_parts(error: yaml.YAMLError) -> tuple[str, str]:
    """(`` line L, column C`` or "", the cause) of a YAML/JSON error."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None)
    if mark is None or problem is None:
        return "", str(error).splitlines()[0] if str(error) else type(error).__name__
    context = getattr(error, "context", None)
    cause = f"{problem} {context}" if context and not isinstance(error, (DuplicateKeyError, NumberTooLongError)) \
        else problem
    return f" line {mark.line + 1}, column {mark.column + 1}", cause


def load_yaml_or_json(path: Path, what: str, *, max_bytes: int | None = None, form: str | None = None) -> Any:
    """Parse a YAML (or JSON, a subset of YAML) file, with an error that names the file, the line and the cause;
    ``form`` (how the file is written) ends the error of a file that is empty or not a mapping."""
    path = Path(path)
    text = read_user_text(path, what, max_bytes=max_bytes)
    try:
        data = parse_yaml(text)
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be a {what} file; fix the syntax") from None
    except (DuplicateKeyError, NumberTooLongError) as e:
        where, cause = yaml_error_parts(e)
        raise InputError(f"{path}{where}: {cause}") from None
    except yaml.YAMLError as e:
        where, cause = yaml_error_parts(e)
        raise InputError(f"{path}{where}: not valid YAML/JSON ({cause}); fix the syntax") from None
    if not isinstance(data, dict):
        if form is None:
            raise InputError(f"{path}: expected a mapping at the top level of the {what} file")
        if data is None:
            raise InputError(f"{path}: the {what} file is empty; {form}")
        found = f"the text {_shortened(data)!r}" if isinstance(data, str) else f"a {type(data).__name__}"
        raise InputError(f"{path}: expected a mapping at the top level of the {what} file, found {found}; {form}")
    return data


def _shortened(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[:limit] + "..."
