"""Disjoint sets (union-find) over hashable items: the rig groups of the diagnostics and the spanning tree of
the pair selection."""

from __future__ import annotations

from collections.abc import Hashable, Iterable


class DisjointSets:
    """Union-find with path halving; items are kept in the order given."""

    def __init__(self, items: Iterable[Hashable]):
        self._parent = {item: item for item in items}

    def find(self, item: Hashable) -> Hashable:
        parent = self._parent
        while parent[item] != item:
            parent[item] = parent[parent[item]]
            item = parent[item]
        return item

    def union(self, a: Hashable, b: Hashable) -> bool:
        """Join the sets of ``a`` and ``b``; False when they were one already."""
        root_a, root_b = self.find(a), self.find(b)
        if root_a == root_b:
            return False
        self._parent[root_a] = root_b
        return True

    def groups(self) -> list[list]:
        """The sets, each in the items' order, in the order of their first item."""
        groups: dict[Hashable, list] = {}
        for item in self._parent:
            groups.setdefault(self.find(item), []).append(item)
        return list(groups.values())
