"""``rigsfm explore``: a local page (127.0.0.1 only) on a finished result: the narrow images of one synchronised frame
side by side; a click shows its calibrated band in every other view and its ray's trace on the floor map; clicks of
one person in two or more views are triangulated; every labelled click is saved to the labels CSV at once.

Only fixed names are served: the page, its script and style, and the frame's narrow images by their index in the
model (never a path taken from the request).
"""

from __future__ import annotations

import json
import logging
import math
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, urlparse

from rigsfm.core.errors import RigsfmError
from rigsfm.core.local_server import SHARED_FILES, LocalHandler, LocalServer, image_bytes
from rigsfm.core.workspace import os_error_text
from rigsfm.explore.session import ExploreOptions, ExploreSession

logger = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
FILES = {"/": "index.html", "/index.html": "index.html", "/explore.js": "explore.js", "/explore.css": "explore.css"}


class _Handler(LocalHandler):
    session: ExploreSession  # set on the subclass made per server
    server_version = "rigsfm-explore"

    def do_GET(self) -> None:
        if not self._host_ok():
            return
        url = urlparse(self.path)
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        frame = query.get("frame")
        try:
            if url.path in FILES:
                self._static(STATIC / FILES[url.path])
            elif url.path in SHARED_FILES:
                self._static(SHARED_FILES[url.path])
            elif url.path == "/image":
                names = self.session.result.frame_names(frame or self.session.frame)
                view = int(query["view"])
                if not 0 <= view < len(names):
                    raise ValueError(f"view {view} is not one of the {len(names)} views")
                # views: images
                self._send(*image_bytes(self.session.result.images_dir / names[view]))  # type: ignore[operator]
            elif url.path == "/api/state":
                if query.get("reload") == "1":
                    self.session.reload()
                self._json(self.session.state(frame))
            elif url.path == "/api/band":
                x, y = float(query["x"]), float(query["y"])
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError("x and y must be finite numbers")
                self._json(self.session.bands(frame, int(query["view"]), x, y))
            else:
                self._json({"error": "not found"}, HTTPStatus.NOT_FOUND)
        except (RigsfmError, KeyError, ValueError) as error:
            self._json({"error": str(error)}, HTTPStatus.BAD_REQUEST)

    def do_PUT(self) -> None:
        raw = self._put_body("/api/labels")
        if raw is None:
            return
        try:
            body = json.loads(raw or b"{}")
            if not isinstance(body, dict) or "labels" not in body or not isinstance(body.get("frame"), str):
                raise ValueError('expected {"frame": NAME, "labels": [{"image", "x", "y", "person"}, ...]}')
            self._json(self.session.set_frame_labels(body["frame"], body["labels"]))
        except OSError as error:  # the request was fine, the CSV could not be written: name it, not a temporary file
            csv = self.session.csv_path
            blocked = any(folder.exists() and not folder.is_dir() for folder in csv.parents)  # mkdir says EEXIST
            cause = "a part of the path is a file, not a folder" if blocked else os_error_text(error)
            self._json({"error": f"cannot save to {csv}: {cause}; nothing was saved: fix the folder (or restart "
                                 "with another --labels) and click again"}, HTTPStatus.INTERNAL_SERVER_ERROR)
        except (RigsfmError, ValueError, RecursionError) as error:
            self._json({"error": str(error) or type(error).__name__}, HTTPStatus.BAD_REQUEST)


class ExploreServer(LocalServer):
    """The HTTP server in a daemon thread; ``url`` to open, ``close()`` to stop."""

    def __init__(self, session: ExploreSession, port: int = 0):
        self.session = session
        super().__init__(type("ExploreHandler", (_Handler,), {"session": session}), port, "rigsfm-explore")


def start_explorer(out: Path, options: ExploreOptions = ExploreOptions(), *, port: int = 0) -> ExploreServer:
    return ExploreServer(ExploreSession(Path(out), options), port)
