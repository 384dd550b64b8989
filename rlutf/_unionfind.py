"""Groups of items joined by pairs (union-find), each named by its smallest item."""

from __future__ import annotations

from collections.abc import Iterable


def group_roots(count: int, pairs: Iterable[tuple[int, int]]) -> list[int]:
    """For each of ``count`` items, the smallest item of its group, the groups being what
    ``pairs`` join, transitively."""
    parent = list(range(count))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs:
        a, b = root(i), root(j)
        if a != b:
            parent[max(a, b)] = min(a, b)
    return [root(i) for i in range(count)]
