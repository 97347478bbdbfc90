"""The suite's xdist scheduling (tests/scheduling.py): a module's tests run on one worker, the Ray modules on the
same one. Run on a small suite of its own, in a pytest with two workers (the plain ``loadgroup`` of pytest-xdist
3.8 under pytest 9.2 fails this: every test is its own unit and the modules' tests alternate between workers)."""

import re
import subprocess
import sys
from pathlib import Path

from scheduling import work_unit

CONFTEST = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
from scheduling import ModuleScheduling

class Scheduling(ModuleScheduling):
    together = frozenset({{"test_c", "test_d"}})

def pytest_xdist_make_scheduler(config, log):
    return Scheduling(config, log)
"""
MODULE = "import pytest\n\n@pytest.mark.parametrize('i', range(6))\ndef test_x(i):\n    pass\n"


def test_work_units_are_modules_and_the_ray_modules_share_one():
    assert work_unit("tests/test_world.py::test_a[x::y]") == "tests/test_world.py"
    assert work_unit("tests/test_scale.py::test_b") == work_unit("tests/test_track_rendered.py::test_c") == "together"


def test_each_module_runs_on_one_worker(tmp_path):
    (tmp_path / "conftest.py").write_text(CONFTEST)
    for name in "abcd":
        (tmp_path / f"test_{name}.py").write_text(MODULE)
    out = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-n", "2", "-v", "-o", "addopts=",
                          "--rootdir", str(tmp_path), str(tmp_path)], check=False, capture_output=True, text=True,
                         cwd=tmp_path, timeout=120).stdout
    workers: dict[str, set[str]] = {}
    for worker, module in re.findall(r"\[(gw\d)\].*PASSED.*(test_\w)\.py::", out):
        workers.setdefault(module, set()).add(worker)
    assert sorted(workers) == ["test_a", "test_b", "test_c", "test_d"] and "24 passed" in out, out
    assert all(len(w) == 1 for w in workers.values()), workers
    assert workers["test_c"] == workers["test_d"], workers
