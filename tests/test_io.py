import os
import tempfile
from pathlib import Path

import pytest

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import atomic_directory, write_json_atomic, write_text_atomic
from rigsfm.core.owned import commit, files_under, previous_files


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


def _output(tmp_path: Path, files: dict[str, str]) -> Path:
    """A finished temporary folder of ``files`` (relative path -> text), as a command writes it before commit."""
    tmp = Path(tempfile.mkdtemp(dir=tmp_path))
    for name, text in files.items():
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp / name).write_text(text)
    return tmp


def _write(tmp_path: Path, dest: Path, files: dict[str, str], overwrite: bool = True) -> None:
    previous = previous_files(dest, ".m.json", overwrite=overwrite, option="--out", what="output")
    commit(dest, _output(tmp_path, files), previous, ".m.json", {}, option="--out", what="output")


def test_an_output_of_sub_folders_is_replaced_and_only_its_own_files_removed(tmp_path):
    """An output of one folder per frame: a second one with other frames replaces the first's files and removes
    those it does not write again (and their emptied folders); a user's file anywhere in it is refused, with
    nothing written or removed, and an edited file of the output is kept."""
    dest = tmp_path / "persons"
    _write(tmp_path, dest, {"frame0/a.csv": "1", "frame1/a.csv": "1"})
    with pytest.raises(WorkspaceError, match="already holds an output: pass --overwrite"):
        _write(tmp_path, dest, {"frame0/a.csv": "2"}, overwrite=False)
    _write(tmp_path, dest, {"frame0/a.csv": "2", "frame2/a.csv": "2"})
    assert sorted(files_under(dest)) == [".m.json", "frame0/a.csv", "frame2/a.csv"]
    assert (dest / "frame0" / "a.csv").read_text() == "2" and not (dest / "frame1").exists()
    (dest / "frame2" / "notes.txt").write_text("mine")
    with pytest.raises(WorkspaceError, match=r"holds files rigsfm did not write \(frame2/notes.txt\)"):
        _write(tmp_path, dest, {"frame0/a.csv": "3"})
    assert (dest / "frame2" / "a.csv").read_text() == "2"
    (dest / "frame2" / "notes.txt").unlink()
    (dest / "frame0" / "a.csv").write_text("edited")
    with pytest.raises(WorkspaceError, match="is not what an earlier output wrote there"):
        _write(tmp_path, dest, {"frame0/a.csv": "3"})
    _write(tmp_path, dest, {"frame2/a.csv": "3"})  # the edited file is kept, no longer the output's
    assert (dest / "frame0" / "a.csv").read_text() == "edited" and (dest / "frame2" / "a.csv").read_text() == "3"
    with pytest.raises(WorkspaceError, match=r"holds files rigsfm did not write \(frame0/a.csv\)"):
        _write(tmp_path, dest, {"frame2/a.csv": "4"})
