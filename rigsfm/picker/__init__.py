"""``rigsfm pick``: pick correspondences between two wide images in a local browser page."""

from rigsfm.picker.server import PickerServer, pick_command, start_picker
from rigsfm.picker.session import PickerSession

__all__ = ["PickerServer", "PickerSession", "pick_command", "start_picker"]
