"""scripts/setup.sh waits for another package manager (unattended-upgrades right after boot) instead of failing.

The script runs from a copy with `--apt-only`, its lock files replaced by files of the test (RIGSFM_APT_LOCKS)
and apt-get, dpkg-query and sudo by stand-ins on PATH: the machine's apt is never locked or called.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOLD = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o640)
fcntl.lockf(fd, fcntl.LOCK_EX)  # a POSIX lock, as apt and dpkg take
print("held", flush=True)
time.sleep(float(sys.argv[2]))
with open(sys.argv[3], "a") as log:
    log.write("released\\n")
"""
FAKE_APT_GET = """#!/bin/sh
echo "apt-get $*" >> "$APT_LOG"
case "$*" in *install*)
  echo "debconf: delaying package configuration, since apt-utils is not installed" >&2
  echo "W: a real warning" >&2 ;;
esac
"""

pytestmark = pytest.mark.skipif(not Path("/proc/locks").exists() or shutil.which("apt-get") is None,
                                reason="needs Linux's /proc/locks and an apt system")


@pytest.fixture
def setup_copy(tmp_path):
    (tmp_path / "repo" / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "setup.sh", tmp_path / "repo" / "scripts" / "setup.sh")
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    for name, text in {"apt-get": FAKE_APT_GET, "dpkg-query": "#!/bin/sh\nexit 1\n",  # nothing installed
                       "sudo": '#!/bin/sh\nexec "$@"\n'}.items():
        (bin_ / name).write_text(text)
        (bin_ / name).chmod(0o755)
    lock, log = tmp_path / "lock-frontend", tmp_path / "apt.log"
    lock.touch()
    log.touch()
    env = {"PATH": f"{bin_}:/usr/sbin:/usr/bin:/sbin:/bin", "HOME": str(tmp_path), "APT_LOG": str(log),
           "RIGSFM_APT_LOCKS": f"{tmp_path / 'missing-lock'} {lock}"}
    return tmp_path / "repo" / "scripts" / "setup.sh", lock, log, env


def hold(lock: Path, seconds: float, log: Path) -> subprocess.Popen:
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(lock), str(seconds), str(log)],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_setup_waits_for_the_dpkg_lock_then_installs(setup_copy):
    script, lock, log, env = setup_copy
    holder = hold(lock, 3, log)
    try:
        done = subprocess.run(["bash", str(script), "--apt-only"], env={**env, "RIGSFM_APT_WAIT": "120"},
                              capture_output=True, text=True, timeout=120)
    finally:
        holder.kill()
        holder.wait()
    assert done.returncode == 0, done.stderr
    waiting = [line for line in done.stderr.splitlines() if "waiting" in line]
    assert len(waiting) == 1, done.stderr
    assert f"process {holder.pid} (python" in waiting[0] and str(lock) in waiting[0]
    calls = log.read_text().splitlines()
    assert calls[0] == "released", calls  # apt-get ran only once the lock was free
    assert [c.split()[3] for c in calls[1:]] == ["update", "install"], calls
    assert all("DPkg::Lock::Timeout=120" in c for c in calls[1:]), calls
    assert "debconf" not in done.stderr and "W: a real warning" in done.stderr  # noise gone, warnings kept


def test_setup_gives_up_after_the_bound_with_one_line(setup_copy):
    script, lock, log, env = setup_copy
    holder = hold(lock, 60, log)
    try:
        done = subprocess.run(["bash", str(script), "--apt-only"], env={**env, "RIGSFM_APT_WAIT": "2"},
                              capture_output=True, text=True, timeout=60)
    finally:
        holder.kill()
        holder.wait()
    assert done.returncode == 1
    last = done.stderr.splitlines()[-1]
    assert last.startswith("setup: gave up after 2 s: ") and f"held by process {holder.pid}" in last, done.stderr
    assert "run setup again" in last
    assert log.read_text() == ""  # apt-get never ran


def test_setup_says_when_the_disk_is_too_full_before_installing(setup_copy):
    script, _, _, env = setup_copy
    done = subprocess.run(["bash", str(script)], env={**env, "RIGSFM_SETUP_NEED_MB": str(10**12)},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    last = done.stderr.splitlines()[-1]
    assert last.startswith("setup: only ") and "MiB free on " + str(script.parents[1]) in last, done.stderr
    assert "free some space and run setup again" in last
    assert not (script.parents[1] / ".venv").exists()  # nothing half-installed
