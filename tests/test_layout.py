"""The house plan (ARCHITECTURE in docs/): service/ in rooms along the frame's path, and no
import circles in service/ or client/ (imports inside functions and under TYPE_CHECKING count)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ROOMS = {"api", "vision", "maps", "estimators", "engine", "http", "zenoh", "demo"}
TOP = {"__init__", "__main__", "cli", "server", "settings"}


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def import_graph(packages: tuple[str, ...] = ("service", "client")) -> dict[str, set[str]]:
    """module -> the modules of ``packages`` it imports, anywhere in its body."""
    files = [p for pkg in packages for p in sorted((ROOT / pkg).rglob("*.py"))]
    mods = {_module(p): p for p in files}
    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            for n in names:
                while n and n not in mods:  # the longest prefix that is one of our modules
                    n = n.rpartition(".")[0]
                if n and n != mod and n.split(".")[0] in packages:
                    deps.add(n)
        graph[mod] = deps
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circles() -> None:
    assert _cycles(import_graph()) == []


def test_service_top_level_is_start_up_only() -> None:
    top = {p.stem for p in (ROOT / "service").glob("*.py")}
    rooms = {p.name for p in (ROOT / "service").iterdir()
             if p.is_dir() and (p / "__init__.py").exists()}
    assert top <= TOP, top - TOP
    assert rooms == ROOMS
    assert len(top) + len(rooms) <= 12 + 1  # the modules, the rooms and the demo data


def test_rooms_say_what_they_own() -> None:
    for room in ROOMS:
        doc = ast.get_docstring(ast.parse((ROOT / "service" / room / "__init__.py").read_text()))
        assert doc, room


def _deps_of(room: str, graph: dict[str, set[str]]) -> set[str]:
    return {d for m, ds in graph.items() if m.startswith(f"service.{room}") for d in ds}


def test_import_rules() -> None:
    """api imports nothing of ours; estimators see no engine or transport; the engine knows
    neither fastapi nor zenoh; the base client imports service.api only."""
    g = import_graph()
    assert {d for d in _deps_of("api", g) if not d.startswith("service.api")} == set()
    assert {d for d in _deps_of("estimators", g)
            if d.startswith(("service.engine", "service.http", "service.zenoh"))} == set()
    assert {d for d in _deps_of("engine", g)
            if d.startswith(("service.http", "service.zenoh"))} == set()
    for path in (ROOT / "service" / "engine").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""])
                assert not any(n.split(".")[0] in ("fastapi", "starlette", "zenoh")
                               for n in names), (path, names)


def test_base_client_imports_service_api_only() -> None:
    """At import time the robot-side client needs ``service.api`` alone; the rest of the
    service is imported inside the functions of the extras that use it."""
    offenders = []
    for path in sorted((ROOT / "client").glob("*.py")):
        if path.stem == "cli":  # the whole project's command line: every import is lazy
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("service"):
                if not (node.module or "").startswith("service.api"):
                    offenders.append(f"{path.name}: {node.module}")
    assert offenders == []
