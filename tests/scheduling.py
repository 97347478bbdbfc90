"""How pytest-xdist spreads this suite over its workers: one work unit per test module, so a module's fixtures
(rendered scenes, runs) are made once, on one worker; the modules that start Ray form one unit (two Ray instances
started at once on one machine compete).

Not ``--dist loadgroup``: it groups through a suffix it writes into ``item._nodeid``, which pytest >= 9.2 no
longer reads (nodeids live in ``item._id``), so every test became its own unit and the module fixtures were made
on both workers, some several times (measured: the manual-matches scenes rendered twice, the world arena run
twice). ``tests/test_scheduling.py`` runs a small suite with this scheduler to pin it.
"""

from __future__ import annotations

from pathlib import PurePosixPath

from xdist.scheduler import LoadScopeScheduling

RAY_MODULES = frozenset({"test_track_rendered", "test_scale"})


def work_unit(nodeid: str, together: frozenset[str] = RAY_MODULES) -> str:
    """The work unit of a test: its module's path, or ``"together"`` for the modules in ``together``."""
    module = nodeid.split("::", 1)[0]
    return "together" if PurePosixPath(module).stem in together else module


class ModuleScheduling(LoadScopeScheduling):
    """xdist's ``loadscope`` with the scope of :func:`work_unit` (modules; the Ray modules together)."""

    together = RAY_MODULES

    def _split_scope(self, nodeid: str) -> str:
        return work_unit(nodeid, self.together)
