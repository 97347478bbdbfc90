"""The local page servers' common pieces (``rigsfm pick``, ``rigsfm explore``): an HTTP server on 127.0.0.1 only,
in a daemon thread, whose handler answers only a Host of 127.0.0.1 or localhost (a page elsewhere cannot reach it
through DNS rebinding), serves fixed names only (no request path becomes a file path) and images as the browser
must show them; ``static/page.js`` and ``static/page.css`` are the pages' common script (requests, SVG, views
that zoom, pan and take clicks) and layout, which each server serves as ``/page.js`` and ``/page.css``
(``SHARED_FILES``).
"""

from __future__ import annotations

import errno
import json
import logging
import mimetypes
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlparse

import cv2

from rigsfm.core.errors import InputError, RigsfmError
from rigsfm.core.image_files import exif_orientation, is_turned, read_image
from rigsfm.core.workspace import os_error_text

logger = logging.getLogger(__name__)

BROWSER_FORMATS = {".png", ".jpg", ".jpeg", ".bmp"}
MAX_BODY = 5_000_000
SHARED_FILES = {f"/{name}": Path(__file__).resolve().parent / "static" / name  # every page loads these
                for name in ("page.js", "page.css")}


def image_bytes(path: Path) -> tuple[bytes, str]:
    """The file as the browser gets it: its own bytes where the browser shows them as stored, else a PNG of the
    stored pixels (a browser turns a JPEG by its EXIF Orientation, and the clicks are in the stored frame)."""
    if path.suffix.lower() in BROWSER_FORMATS and not is_turned(exif_orientation(path)):
        return path.read_bytes(), mimetypes.guess_type(path.name)[0] or "image/png"
    image = read_image(path, cv2.IMREAD_UNCHANGED)
    ok, data = (False, None) if image is None else cv2.imencode(".png", image)
    if not ok:
        raise RigsfmError(f"{path}: cannot be converted for the browser")
    return data.tobytes(), "image/png"  # type: ignore[union-attr]  # ok: data is set


class LocalHandler(BaseHTTPRequestHandler):
    """Replies and checks every local page needs; subclasses add ``do_GET``/``do_PUT``."""

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

    def _static(self, path: Path) -> None:
        kinds = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}
        self._send(path.read_bytes(), f"{kinds[path.suffix]}; charset=utf-8")

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        if host in ("127.0.0.1", "localhost"):
            return True
        self._json({"error": "forbidden host"}, HTTPStatus.FORBIDDEN)
        return False

    def _body_length(self) -> int | None:
        """The request body's size, or None after answering a missing or too large one."""
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if length < 0:
            self._json({"error": "a Content-Length header with the body's size is needed"}, HTTPStatus.BAD_REQUEST)
            return None
        if length > MAX_BODY:
            self._json({"error": "request too large"}, HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
            return None
        return length


    def _put_body(self, path: str) -> bytes | None:
        """The body of a PUT to ``path``, or None after answering a foreign host, another path or a bad size."""
        if not self._host_ok():
            return None
        if urlparse(self.path).path != path:
            self._json({"error": "not found"}, HTTPStatus.NOT_FOUND)
            return None
        length = self._body_length()
        return None if length is None else self.rfile.read(length)


class LocalServer:
    """The HTTP server on 127.0.0.1 in a daemon thread; ``url`` to open, ``close()`` to stop."""

    def __init__(self, handler: type[LocalHandler], port: int = 0, name: str = "rigsfm-page"):
        try:
            self.httpd = ThreadingHTTPServer(("127.0.0.1", port), handler)
        except OSError as error:
            why = "the port is in use" if error.errno == errno.EADDRINUSE else os_error_text(error)
            raise InputError(f"cannot serve on 127.0.0.1:{port} ({why}); choose another --port, or 0 for a free "
                             "one") from None
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, name=name, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)
