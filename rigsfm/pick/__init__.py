"""``rigsfm pick``: pick correspondences between two wide images in a local browser page."""

from rigsfm.pick.server import PickerServer, pick_command, start_picker
from rigsfm.pick.session import PickerSession

__all__ = ["PickerServer", "PickerSession", "pick_command", "start_picker"]
