"""The layout of ``service/``: imports go one way, and modules stay small.

Every import is counted, lazy ones inside functions and ``TYPE_CHECKING`` ones too, since any of
them can close a circle.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

SERVICE = Path(__file__).resolve().parents[2] / "service"

#: What each part of ``service`` may import (besides itself, ``rlutf`` and ``schemas``); the
#: sub-packages' docstrings say the same.
ALLOWED: dict[str, set[str]] = {
    "keys": set(),
    "config": set(),
    "relocalization": set(),
    "maphealth": {"keys"},
    "engine": {"keys", "relocalization", "maphealth"},
    "maps": {"keys"},
    "cluster": {"keys"},
    "logs": {"keys", "config", "engine", "relocalization", "maphealth", "maps"},
    "ros2": {"keys", "config", "engine", "relocalization", "maphealth", "maps", "logs"},
    "live": {
        "keys",
        "config",
        "engine",
        "relocalization",
        "maphealth",
        "maps",
        "logs",
        "cluster",
        "ros2",
    },
    "cli": {
        "keys",
        "config",
        "engine",
        "relocalization",
        "maphealth",
        "maps",
        "logs",
        "cluster",
        "live",
        "ros2",
    },
    "__main__": {"cli"},
}


def _module_name(path: Path) -> str:
    parts = ["service", *path.relative_to(SERVICE).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(SERVICE.rglob("*.py"))}


def _imports(path: Path, name: str, known: set[str]) -> Iterator[str]:
    """The ``service`` modules that ``path`` (module ``name``) imports."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            # ``from package import module`` names a module; otherwise the module itself.
            targets = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known]
            targets = targets or [base]
        else:
            continue
        for target in targets:
            module = target
            while module and module not in known:
                module = module.rpartition(".")[0]
            if module and module != name:
                yield module


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: set(_imports(path, name, known)) for name, path in modules.items()}


def _part(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_circle_of_imports_between_modules() -> None:
    assert _cycles(_graph()) == []


def test_no_circle_of_imports_between_parts() -> None:
    parts: dict[str, set[str]] = {}
    for module, targets in _graph().items():
        parts.setdefault(_part(module), set()).update(_part(t) for t in targets)
    for part, targets in parts.items():
        targets.discard(part)
    assert _cycles(parts) == []


def test_each_part_imports_only_what_it_may() -> None:
    wrong = [
        f"{module} imports {target}"
        for module, targets in _graph().items()
        if module != "service"
        for target in sorted(targets)
        if _part(target) != _part(module) and _part(target) not in ALLOWED[_part(module)]
    ]
    assert wrong == []


def test_every_part_is_known() -> None:
    assert {_part(m) for m in _modules() if m != "service"} == set(ALLOWED)


def test_at_most_a_dozen_modules_directly_in_service() -> None:
    assert len(list(SERVICE.glob("*.py"))) <= 12


def test_no_module_over_500_lines() -> None:
    lines = {
        str(p.relative_to(SERVICE)): len(p.read_text(encoding="utf-8").splitlines())
        for p in SERVICE.rglob("*.py")
    }
    assert {name: n for name, n in lines.items() if n > 500} == {}
