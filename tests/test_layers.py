"""The layering, read from the source: every import of every project module (at the top, in a
function or under ``TYPE_CHECKING``), checked against one direction per arrow, and no cycle.

- ``rovergate/``, the base, imports no other package of the project;
- the module packages (``rover_sim/``, ``mapper/``, ``gate/``, ``planner/``) meet only through
  the base: each imports itself and the base;
- ``ecosystem/`` is fed by the mission: it imports itself and the base, no module package;
- ``mission/``, the composition root, may import all of them; its transports (the runtime's
  routing, process set, supervisor, launcher, inbox, journal, clock) do not import
  ``ecosystem/``;
- ``mission/`` holds no file outside a sub-package but its entry points.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BASE = "rovergate"
MODULES = ("rover_sim", "mapper", "gate", "planner")
PACKAGES = (BASE, *MODULES, "ecosystem", "mission")
#: May import these packages (besides itself).
ALLOWED: dict[str, tuple[str, ...]] = {
    BASE: (), **{m: (BASE,) for m in MODULES}, "ecosystem": (BASE,), "mission": PACKAGES,
}
TRANSPORT = ("mission.runtime.transport", "mission.runtime.process_set",
             "mission.runtime.supervisor", "mission.runtime.launcher", "mission.runtime.inbox",
             "mission.runtime.journal", "mission.runtime.clock")
MISSION_ENTRY_POINTS = {"__init__.py", "cli.py", "run.py", "script.py"}


def module_files(root: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of the project's packages under ``root``."""
    out = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imports(root: Path) -> dict[str, set[str]]:
    """Module -> the project modules it imports (a name imported from a package that is a
    module of its own counts as that module)."""
    files = module_files(root)

    def known(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        found: set[str] = set()
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package[:len(package) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base
                           for a in node.names]
            else:
                continue
            found.update(t for t in map(known, targets) if t and t != name)
        graph[name] = found
    return graph


def wrong_arrows(graph: dict[str, set[str]]) -> list[str]:
    out = []
    for src, targets in sorted(graph.items()):
        a = src.split(".")[0]
        for dst in sorted(targets):
            b = dst.split(".")[0]
            if b != a and b not in ALLOWED[a]:
                out.append(f"{src} imports {dst}: {a}/ may import only "
                           f"{', '.join(ALLOWED[a]) or 'itself'}")
            elif src in TRANSPORT and b == "ecosystem":
                out.append(f"{src} imports {dst}: the transport does not import ecosystem/")
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected set of two or more modules (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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


def test_every_arrow_points_one_way():
    bad = wrong_arrows(imports(ROOT))
    assert not bad, "wrong arrows:\n" + "\n".join(bad)


def test_no_import_cycle():
    found = cycles(imports(ROOT))
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_the_mission_package_keeps_its_rooms():
    loose = sorted(p.name for p in (ROOT / "mission").glob("*.py")
                   if p.name not in MISSION_ENTRY_POINTS)
    assert not loose, f"mission/ files outside a sub-package: {loose}"


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return tmp_path


@pytest.mark.parametrize("files, expected", [
    ({"rovergate/x.py": "def f():\n    from mission.script import Mission\n",
      "mission/script.py": ""}, "rovergate.x imports mission.script"),
    ({"ecosystem/v.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                        "    from rover_sim.scene import Scene\n",
      "rover_sim/scene.py": ""}, "ecosystem.v imports rover_sim.scene"),
    ({"mapper/w.py": "from rover_sim import world\n", "rover_sim/world.py": ""},
     "mapper.w imports rover_sim.world"),
    ({"mission/runtime/__init__.py": "", "mission/runtime/transport.py": "from ..x import y\n",
      "mission/x.py": "", "ecosystem/y.py": ""}, None),
    ({"mission/runtime/__init__.py": "",
      "mission/runtime/transport.py": "from ecosystem.taps import Deferred\n",
      "ecosystem/taps.py": ""}, "mission.runtime.transport imports ecosystem.taps"),
])
def test_a_wrong_arrow_is_found(tmp_path: Path, files: dict[str, str], expected: str | None):
    bad = wrong_arrows(imports(_tree(tmp_path, files)))
    if expected is None:
        assert bad == []
    else:
        assert len(bad) == 1 and bad[0].startswith(expected), bad


def test_a_cycle_is_found(tmp_path: Path):
    root = _tree(tmp_path, {"gate/a.py": "from gate import b\n",
                            "gate/b.py": "def f():\n    from gate.c import g\n",
                            "gate/c.py": "from .a import x\n"})
    assert cycles(imports(root)) == [["gate.a", "gate.b", "gate.c"]]
