"""What several test modules share: the real test images in the repository, and the browser."""

from __future__ import annotations

import shutil
from pathlib import Path

REAL_STEREO = Path(__file__).resolve().parent / "data" / "opencv-stereo"  # OpenCV's real stereo pairs
BROWSER_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update"]


def launch_chromium(playwright):
    """Headless Chromium: Debian's (/usr/bin/chromium, installed by scripts/setup.sh) or, where the
    distribution has none (Ubuntu ships a snap), the build scripts/setup.sh installed with Playwright."""
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable and "/snap/" in str(Path(executable).resolve()):
        executable = None  # a snap wrapper cannot be driven headless from here: use Playwright's build
    return playwright.chromium.launch(executable_path=executable, headless=True, args=BROWSER_ARGS)


def start_local_ray(num_cpus: int = 2) -> None:
    """A fresh local Ray instance for a test (``address="local"``: never a cluster another test or program left
    running), with a small object store; a failure names Ray's own reason and the tail of its logs instead of
    ray.init's long traceback."""
    import ray

    try:
        ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                 object_store_memory=200 * 1024**2)
    except Exception as error:  # noqa: BLE001 - reported with Ray's logs, then the test fails
        logs = sorted(Path("/tmp/ray/session_latest/logs").glob("*.err")) + sorted(
            Path("/tmp/ray/session_latest/logs").glob("*.out"))
        tails = "\n".join(f"--- {p.name}: {p.read_text(errors='replace')[-600:]}" for p in logs[:6])
        import pytest

        pytest.fail(f"ray.init failed: {type(error).__name__}: {str(error)[:800]}\n{tails}", pytrace=False)
