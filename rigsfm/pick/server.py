"""``rigsfm pick``: a local page (127.0.0.1 only) to pick correspondences between two wide images.

The page (``static/``, vanilla JS, no network access beyond this server) shows both images with zoom;
click a point in one image and its partner in the other. From eight pairs on, the epipolar line of
the point being placed is drawn in the other image, and pairs whose Sampson distance exceeds
``--flag-px`` are flagged. Every change is saved to the CSV at once (atomically); undo works and a
reload of the page (or a new ``rigsfm pick`` after a crash) starts from the CSV.
"""

from __future__ import annotations

import json
import logging
import math
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, urlparse

from rigsfm.core.errors import RigsfmError
from rigsfm.core.io import real_path
from rigsfm.core.local_server import SHARED_FILES, LocalHandler, LocalServer
from rigsfm.core.local_server import image_bytes as _image_bytes
from rigsfm.core.rig import load_rigs
from rigsfm.core.workspace import os_error_text
from rigsfm.pick.session import PickerSession, SaveFailed, StalePage, picker_image

logger = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"


class _Handler(LocalHandler):
    session: PickerSession  # set on the subclass made per server
    server_version = "rigsfm-pick"

    def do_GET(self) -> None:
        if not self._host_ok():
            return
        url = urlparse(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        try:
            if url.path in ("/", "/index.html"):
                self._static(STATIC / "index.html")
            elif url.path in ("/picker.js", "/picker.css"):
                self._static(STATIC / url.path[1:])
            elif url.path in SHARED_FILES:
                self._static(SHARED_FILES[url.path])
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
        raw = self._put_body("/api/pairs")
        if raw is None:
            return
        try:
            body = json.loads(raw or b"{}")
            if not isinstance(body, dict) or "pairs" not in body:
                raise ValueError('expected {"pairs": [[x_a, y_a, x_b, y_b], ...]}')
            self._json(self.session.set_pairs(body["pairs"], body.get("revision")))
        except StalePage as error:
            self._json({"error": str(error), "stale": True}, HTTPStatus.CONFLICT)
        except SaveFailed as error:
            self._json({"error": str(error)}, HTTPStatus.INTERNAL_SERVER_ERROR)
        except OSError as error:  # the CSV unreadable: the page is told, the terminal gets no traceback
            where = f"{real_path(error.filename)}: " if error.filename else ""
            self._json({"error": f"{where}{os_error_text(error)}"}, HTTPStatus.INTERNAL_SERVER_ERROR)
        except (RigsfmError, ValueError, RecursionError) as error:
            self._json({"error": str(error) or type(error).__name__}, HTTPStatus.BAD_REQUEST)


class PickerServer(LocalServer):
    """The HTTP server in a daemon thread; ``url`` to open, ``close()`` to stop."""

    def __init__(self, session: PickerSession, port: int = 0):
        self.session = session
        super().__init__(type("PickerHandler", (_Handler,), {"session": session}), port, "rigsfm-pick")


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
