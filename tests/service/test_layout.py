"""The layout of ``service/`` and ``bench/``: imports go one way, and modules stay small.

Every import is counted, lazy ones inside functions and ``TYPE_CHECKING`` ones too, since any of
them can close a circle.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SERVICE = ROOT / "service"
BENCH = ROOT / "bench"

#: What each part of ``service`` may import (besides itself, ``rlutf`` and ``schemas``); the
#: sub-packages' docstrings say the same.
ALLOWED: dict[str, set[str]] = {
    "keys": set(),
    "yamlfile": set(),
    "infile": set(),
    "cores": set(),
    "kernelcache": set(),
    "guard": {"keys", "maphealth"},
    "config": {"guard", "cores", "yamlfile", "infile"},
    "relocalization": set(),
    "maphealth": {"keys"},
    "evidence": {"maphealth"},
    "prepared": set(),
    "engine": {"keys", "relocalization", "guard", "prepared", "maphealth"},
    "maps": {"keys", "yamlfile", "infile"},
    "cluster": {"keys", "infile"},
    "logs": {
        "keys",
        "config",
        "engine",
        "relocalization",
        "maps",
        "guard",
        "maphealth",
        "yamlfile",
        "infile",
    },
    "ros2": {
        "keys",
        "config",
        "engine",
        "relocalization",
        "maps",
        "logs",
        "guard",
        "maphealth",
        "infile",
    },
    "live": {
        "keys",
        "cores",
        "config",
        "engine",
        "relocalization",
        "maphealth",
        "evidence",
        "maps",
        "logs",
        "cluster",
        "ros2",
        "guard",
    },
    # the simulated fleet is a client of the service, as the command line is
    "sim": {"keys", "cores", "config", "maps", "logs", "live", "ros2", "guard"},
    "cli": {
        "cores",
        "infile",
        "kernelcache",
        "guard",
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
        "sim",
    },
    "__main__": {"cli"},
}


def _module_name(path: Path, package: Path = SERVICE) -> str:
    parts = [package.name, *path.relative_to(package).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(package: Path = SERVICE) -> dict[str, Path]:
    return {_module_name(p, package): p for p in sorted(package.rglob("*.py"))}


def _imports(path: Path, name: str, known: set[str]) -> Iterator[str]:
    """The modules of ``known`` that ``path`` (module ``name``) imports."""
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


def _graph(package: Path = SERVICE) -> dict[str, set[str]]:
    modules = _modules(package)
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
    modules = [p for p in SERVICE.glob("*.py") if not p.name.startswith("__")]  # not the package's
    assert len(modules) <= 12, sorted(p.name for p in modules)


def _long_modules(package: Path) -> dict[str, int]:
    lines = {
        str(p.relative_to(package)): len(p.read_text(encoding="utf-8").splitlines())
        for p in package.rglob("*.py")
    }
    return {name: n for name, n in lines.items() if n > 500}


def test_no_module_over_500_lines() -> None:
    assert _long_modules(SERVICE) == {}


def test_no_bench_module_over_500_lines() -> None:
    assert _long_modules(BENCH) == {}


def test_no_circle_of_imports_between_bench_modules() -> None:
    assert _cycles(_graph(BENCH)) == []


def test_the_circle_finder_finds_a_circle(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from pkg import b\n")
    (package / "b.py").write_text("def f():\n    from pkg.a import x\n")
    (package / "c.py").write_text("import pkg.a\n")
    assert _cycles(_graph(package)) == [["pkg.a", "pkg.b"]]
