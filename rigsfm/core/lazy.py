"""Package faces that import their modules only when a name is used (``rigsfm --help`` stays fast)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, exports: dict[str, str]) -> tuple[Callable[[str], Any], list[str]]:
    """A module ``__getattr__`` and ``__all__`` for a package whose names live in its modules:
    ``exports`` maps each public name to the module that defines it."""

    def __getattr__(name: str) -> Any:  # any name: its importers see its own type
        if name in exports:
            return getattr(importlib.import_module(exports[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__, sorted(exports)
