"""``rigsfm pick``: a local page (127.0.0.1 only) to pick correspondences between two wide images.

The page (``static/``, vanilla JS, no network access beyond this server) shows both images with zoom;
click a point in one image and its partner in the other. From eight pairs on, the epipolar line of
the point being placed is drawn in the other image, and pairs whose Sampson distance exceeds
``--flag-px`` are flagged. Every change is saved to the CSV at once (atomically); undo works and a
reload of the page (or a new ``rigsfm pick`` after a crash) starts from the CSV.
"""

from __future__ import annotations

import errno
import json
import math
import logging
import mimetypes
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import cv2

from rigsfm.core.errors import InputError, RigsfmError
from rigsfm.core.image_files import exif_orientation, is_turned, read_image
from rigsfm.core.workspace import os_error_text
from rigsfm.pick.session import PickerSession, SaveFailed, StalePage, picker_image
from rigsfm.core.rig import load_rigs

logger = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
BROWSER_FORMATS = {".png", ".jpg", ".jpeg", ".bmp"}
MAX_BODY = 5_000_000


def _image_bytes(path: Path) -> tuple[bytes, str]:
    """The file as the browser gets it: its own bytes where the browser shows them as stored, else a PNG of the
    stored pixels (a browser turns a JPEG by its EXIF Orientation, and the clicks are in the stored frame)."""
    if path.suffix.lower() in BROWSER_FORMATS and not is_turned(exif_orientation(path)):
        return path.read_bytes(), mimetypes.guess_type(path.name)[0] or "image/png"
    image = read_image(path, cv2.IMREAD_UNCHANGED)
    ok, data = (False, None) if image is None else cv2.imencode(".png", image)
    if not ok:
        raise RigsfmError(f"{path}: cannot be converted for the browser")
    return data.tobytes(), "image/png"


class _Handler(BaseHTTPRequestHandler):
    session: PickerSession  # set on the subclass made per server
    server_version = "rigsfm-pick"

    def log_message(self, fmt: str, *args) -> None:  # keep the terminal quiet; debug log only
        logger.debug("%s " + fmt, self.address_string(), *args)

    def _send(self, body: bytes, content_type: str, status: int = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, data, status: int = HTTPStatus.OK) -> None:
        self._send(json.dumps(data).encode(), "application/json", status)

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        if host in ("127.0.0.1", "localhost"):
            return True
        self._json({"error": "forbidden host"}, HTTPStatus.FORBIDDEN)
        return False

    def do_GET(self) -> None:
        if not self._host_ok():
            return
        url = urlparse(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        try:
            if url.path in ("/", "/index.html"):
                self._send((STATIC / "index.html").read_bytes(), "text/html; charset=utf-8")
            elif url.path in ("/picker.js", "/picker.css"):
                kind = "text/javascript" if url.path.endswith(".js") else "text/css"
                self._send((STATIC / url.path[1:]).read_bytes(), f"{kind}; charset=utf-8")
            elif url.path in ("/image/a", "/image/b"):
                self._send(*_image_bytes(self.session.images[0 if url.path.endswith("a") else 1].path))
            elif url.path == "/api/state":
                if query.get("reload") == "1":
                    self.session.reload()
                self._json(self.session.state())
            elif url.path == "/api/epipolar":
                side = query.get("side", "a")
                if side not in ("a", "b"):
                    raise ValueError("side must be a or b")
                x, y = float(query["x"]), float(query["y"])
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError("x and y must be finite numbers")
                self._json({"side": side, "polyline": self.session.epipolar(side, x, y)})
            else:
                self._json({"error": "not found"}, HTTPStatus.NOT_FOUND)
        except (RigsfmError, KeyError, ValueError) as error:
            self._json({"error": str(error)}, HTTPStatus.BAD_REQUEST)

    def do_PUT(self) -> None:
        if not self._host_ok():
            return
        if urlparse(self.path).path != "/api/pairs":
            self._json({"error": "not found"}, HTTPStatus.NOT_FOUND)
            return
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if length < 0:
            self._json({"error": "a Content-Length header with the body's size is needed"}, HTTPStatus.BAD_REQUEST)
            return
        if length > MAX_BODY:
            self._json({"error": "request too large"}, HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
            return
        try:
            body = json.loads(self.rfile.read(length) or b"{}")
            if not isinstance(body, dict) or "pairs" not in body:
                raise ValueError('expected {"pairs": [[x_a, y_a, x_b, y_b], ...]}')
            self._json(self.session.set_pairs(body["pairs"], body.get("revision")))
        except StalePage as error:
            self._json({"error": str(error), "stale": True}, HTTPStatus.CONFLICT)
        except SaveFailed as error:
            self._json({"error": str(error)}, HTTPStatus.INTERNAL_SERVER_ERROR)
        except OSError as error:  # the CSV unreadable: the page is told, the terminal gets no traceback
            where = f"{error.filename}: " if error.filename else ""
            self._json({"error": f"{where}{os_error_text(error)}"}, HTTPStatus.INTERNAL_SERVER_ERROR)
        except (RigsfmError, ValueError, RecursionError) as error:
            self._json({"error": str(error) or type(error).__name__}, HTTPStatus.BAD_REQUEST)


class PickerServer:
    """The HTTP server in a daemon thread; ``url`` to open, ``close()`` to stop."""

    def __init__(self, session: PickerSession, port: int = 0):
        handler = type("PickerHandler", (_Handler,), {"session": session})
        self.session = session
        try:
            self.httpd = ThreadingHTTPServer(("127.0.0.1", port), handler)
        except OSError as error:
            why = "the port is in use" if error.errno == errno.EADDRINUSE else os_error_text(error)
            raise InputError(f"cannot serve on 127.0.0.1:{port} ({why}); choose another --port, or 0 for a free "
                             "one") from None
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="rigsfm-pick", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)


def start_picker(
    image_a: Path,
    image_b: Path,
    out: Path,
    rigs_path: Path | None = None,
    port: int = 0,
    flag_px: float = 4.0,
) -> PickerServer:
    rigs = load_rigs(rigs_path) if rigs_path is not None else None
    session = PickerSession(picker_image(image_a, rigs), picker_image(image_b, rigs), out, flag_px)
    return PickerServer(session, port)
