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
