"""``rigsfm pick``: pick correspondences between two wide images in a local browser page.

Library use: ``start_picker(IMAGE_A, IMAGE_B, CSV, rigs.yaml) -> PickerServer`` (``url``, ``close()``).
"""

from rigsfm.core.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "PickerServer": "rigsfm.pick.server",
    "start_picker": "rigsfm.pick.server",
    "PickerSession": "rigsfm.pick.session",
})
