import os

import pytest

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import atomic_directory, write_json_atomic, write_text_atomic


def test_atomic_text_refuses_overwrite_and_keeps_usual_permissions(tmp_path):
    path = write_text_atomic(tmp_path / "a.txt", "one")
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~_umask()
    with pytest.raises(WorkspaceError, match="--overwrite"):
        write_text_atomic(path, "two", overwrite=False)
    assert path.read_text() == "one"
    write_json_atomic(path, {"x": 1})
    assert path.read_text() == '{\n  "x": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_directory_replaces_only_on_success(tmp_path):
    target = tmp_path / "model"
    with atomic_directory(target) as tmp:
        (tmp / "f").write_text("1")
    assert (target / "f").read_text() == "1"
    assert os.stat(target).st_mode & 0o777 == 0o777 & ~_umask()
    with pytest.raises(RuntimeError):
        with atomic_directory(target) as tmp:
            (tmp / "f").write_text("2")
            raise RuntimeError("stage failed")
    assert (target / "f").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask
