"""One error family for everything a user can get wrong.

Every message says what is wrong, where (the file), and what to do about it. The CLI prints
``str(error)`` as one red line and exits non-zero; library callers catch ``RigsfmError``.
"""

from __future__ import annotations


class RigsfmError(Exception):
    """Base class: a problem the user can fix (input, workspace, or a failed reconstruction)."""


class InputError(RigsfmError):
    """An input file or folder is missing, malformed or inconsistent."""


class WorkspaceError(RigsfmError):
    """The output workspace is in a state the command will not touch (e.g. would overwrite)."""


class ReconstructionError(RigsfmError):
    """Structure-from-motion could not produce the requested result from these inputs."""
