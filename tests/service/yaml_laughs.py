"""A YAML "billion laughs": a few hundred bytes whose aliases repeat a value 9 ** levels times."""

from __future__ import annotations


def laughs(levels: int = 10, then: str = "") -> str:
    """A list of nine nested in itself ``levels`` times (anchors ``a0`` .. ``a{levels-1}``),
    then ``then`` (which may use the anchors)."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels)]
    return "\n".join(lines) + "\n" + then
