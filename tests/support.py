"""What several test modules share: the real test images in the repository, EXIF-tagged image files, the
browser, and MVDet's reading of a wildtrack calibration."""

from __future__ import annotations

import contextlib
import shutil
import struct
import zlib
from collections.abc import Iterator
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


@contextlib.contextmanager
def browser_page(server, ready: str, width: int = 1800, height: int = 1100) -> Iterator:
    """A headless Chromium page on a local page server (``rigsfm pick``, ``rigsfm explore``), loaded and ready:
    ``ready`` is the page's promise to wait for. The browser closes on leaving; the server is the caller's."""
    import playwright.sync_api as playwright_api

    with playwright_api.sync_playwright() as p:
        browser = launch_chromium(p)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(server.url)
            page.evaluate(ready)
            yield page
        finally:
            browser.close()


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


def exif_block(orientation: int, big_endian: bool = False) -> bytes:
    """An EXIF payload (``Exif\\0\\0`` and a TIFF structure) whose IFD0 holds only the Orientation tag."""
    e = ">" if big_endian else "<"
    return (b"Exif\x00\x00" + (b"MM" if big_endian else b"II") + struct.pack(e + "HI", 42, 8)
            + struct.pack(e + "H", 1) + struct.pack(e + "HHI", 0x0112, 3, 1) + struct.pack(e + "HH", orientation, 0)
            + struct.pack(e + "I", 0))


def tag_orientation(data: bytes, orientation: int, big_endian: bool = False) -> bytes:
    """A JPEG's or PNG's bytes with an EXIF Orientation tag added, the pixels untouched: a JPEG gets an APP1
    segment after its start marker (as cameras write it), a PNG an eXIf chunk after IHDR."""
    payload = exif_block(orientation, big_endian)
    if data[:2] == b"\xff\xd8":
        return data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:]
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        body = payload[6:]  # PNG's eXIf holds the TIFF structure alone
        chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
        end_of_ihdr = 8 + 8 + struct.unpack(">I", data[8:12])[0] + 4
        return data[:end_of_ihdr] + chunk + data[end_of_ihdr:]
    raise ValueError("tag_orientation takes a JPEG or a PNG")


def write_tagged(path: Path, pixels, orientation: int) -> Path:
    """``pixels`` written as a JPEG or PNG (by ``path``'s suffix) that carries EXIF Orientation ``orientation``."""
    import cv2

    ok, data = cv2.imencode(Path(path).suffix, pixels)
    assert ok
    Path(path).write_bytes(tag_orientation(data.tobytes(), orientation))
    return Path(path)


def mvdet_floor_pixels(calibrations: Path, rig: str, floor_m):
    """OpenCV pixels of floor points (N x 2, metres) read and projected the way MVDet's Wildtrack loader does:
    cv2.FileStorage ``camera_matrix`` from intrinsic_zero (no distortion), ElementTree ``rvec`` / ``tvec`` text from
    extrinsic as float32, world in centimetres, K [R|t] without the z column (get_imagecoord_from_worldcoord)."""
    import xml.etree.ElementTree as ET

    import cv2
    import numpy as np

    fs = cv2.FileStorage(str(calibrations / "intrinsic_zero" / f"intr_{rig}.xml"), cv2.FILE_STORAGE_READ)
    intrinsic = fs.getNode("camera_matrix").mat()
    assert not np.any(fs.getNode("distortion_coefficients").mat())
    fs.release()
    root = ET.parse(calibrations / "extrinsic" / f"extr_{rig}.xml").getroot()
    rvec, tvec = (np.array(list(map(float, root.findall(key)[0].text.lstrip().rstrip().split(" "))), dtype=np.float32)
                  for key in ("rvec", "tvec"))
    extrinsic = np.hstack((cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)))
    project = np.delete(intrinsic @ extrinsic, 2, 1)
    h = np.c_[np.asarray(floor_m) * 100.0, np.ones(len(floor_m))] @ project.T
    return h[:, :2] / h[:, 2:]


def rigsfm_floor_pixels(image, floor_m):
    """OpenCV pixels of floor points (N x 2, metres) through rigsfm's ground homography of a registered image."""
    import numpy as np

    from rigsfm.core.ground import image_from_plane

    h = np.c_[np.asarray(floor_m), np.ones(len(floor_m))] @ image_from_plane(image, 0.0).T
    return h[:, :2] / h[:, 2:] - 0.5  # COLMAP -> OpenCV pixel centres


def picker_images(root: Path) -> list[Path]:
    """Two small random wide images, ROOT/images/rig01|rig02/wide/f0.png, for the picker's tests."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    paths = []
    for rig in ("rig01", "rig02"):
        path = root / "images" / rig / "wide" / "f0.png"
        path.parent.mkdir(parents=True)
        cv2.imwrite(str(path), rng.integers(0, 255, (60, 80), dtype=np.uint8))
        paths.append(path)
    return paths


def as_from_a_terminal() -> None:
    """SIGINT as a terminal's foreground job has it (a shell starts background jobs with SIGINT ignored, and a
    child keeps that): a ``preexec_fn`` for commands a test stops with Ctrl-C."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def worker_threads(_task) -> list[tuple[str, int]]:
    """The thread pools of a pool worker (``rigsfm.core.executors``), after it loads scipy's own OpenBLAS: a library
    loaded after the worker's set-up."""
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_info

    return sorted({(info["internal_api"], info["num_threads"]) for info in threadpool_info()})
