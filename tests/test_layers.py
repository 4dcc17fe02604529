"""Imports go one way: application -> edges -> core, and inside the core from higher layers to lower.

    application  visionpos.app, visionpos.benchmarks, visionpos.cli (compose everything; only
                 `python -m visionpos` imports the CLI). The benchmarks belong here, not in the
                 core: they run the demo and SITL apps (`visionpos bench`: robustness, bridge,
                 console, sitl) and nothing below the application may import them.
    edges        bridge/, stations/, console/ (use the core; never the application, never each other)
    core         every other visionpos package, in the layers of CORE_LAYERS

Every import statement of every module counts, those inside functions too (a lazy import is
still a dependency). Rules are per package (visionpos.geometry.*, visionpos.fusion.*), so
splitting a package into modules does not change them.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOP_PACKAGES = ("visionpos", "bridge", "stations", "console")

# lowest first; a core package imports only packages of lower layers (and itself). Packages in
# one layer are independent of each other.
CORE_LAYERS: list[tuple[str, ...]] = [
    ("visionpos", "visionpos.errors", "visionpos.logutil"),  # the package root holds only __version__
    ("visionpos.jit", "visionpos.messages"),
    ("visionpos.protocol",),
    ("visionpos.camera",),
    ("visionpos.config",),  # parses the cameras of an arena with camera models
    ("visionpos.geometry",),
    ("visionpos.foxglove",),  # the Foxglove channels of recordings: cameras, station packets, rotations
    ("visionpos.fusion", "visionpos.recording"),
    ("visionpos.sim", "visionpos.server"),  # sim writes recordings; the server fuses and records
    ("visionpos.calibration",),  # calibrates from recordings or simulated captures
    ("visionpos.analysis",),  # replays recordings through the server's ingest and fusion
]
APPLICATION = ("visionpos.app", "visionpos.benchmarks", "visionpos.cli", "visionpos.__main__")
EDGES = ("bridge", "stations", "console")
LAYER = {unit: i for i, units in enumerate(CORE_LAYERS) for unit in units}


def unit_of(module: str) -> str:
    """The package a rule is about: 'visionpos.fusion.tracking' -> 'visionpos.fusion', 'bridge.x' -> 'bridge'."""
    parts = module.split(".")
    if parts[0] != "visionpos" or len(parts) == 1:
        return parts[0]
    return "visionpos." + parts[1]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def is_module(name: str) -> bool:
    p = ROOT.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def imported_modules(path: Path) -> set[str]:
    """Every project module that `path` imports, anywhere in it."""
    own = module_name(path)
    package = own if path.name == "__init__.py" else own.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.add(base)
            # `from visionpos import protocol` imports the module visionpos.protocol
            found.update(f"{base}.{a.name}" for a in node.names if is_module(f"{base}.{a.name}"))
    return {m for m in found if m.split(".")[0] in TOP_PACKAGES}


def all_modules() -> list[Path]:
    return sorted(p for top in TOP_PACKAGES for p in (ROOT / top).rglob("*.py"))


def violation(importer: str, imported: str) -> str | None:
    """Why `importer` may not import `imported`, or None when it may."""
    a, b = unit_of(importer), unit_of(imported)
    if a == b:
        return None
    if b in ("visionpos.cli", "visionpos.__main__") and a != "visionpos.__main__":
        return "only `python -m visionpos` imports the CLI"
    if a in APPLICATION:
        return None
    if b in APPLICATION:
        return f"{a} is below the application layer"
    if a in EDGES:
        return f"the edges ({', '.join(EDGES)}) are independent of each other" if b in EDGES else None
    if b in EDGES:
        return "the core never imports the edges"
    if a not in LAYER or b not in LAYER:
        return f"{a if a not in LAYER else b} has no layer in CORE_LAYERS: add it"
    if LAYER[b] >= LAYER[a]:
        return f"{b} (layer {LAYER[b]}) is not below {a} (layer {LAYER[a]})"
    return None


def test_every_package_has_a_layer():
    units = {unit_of(module_name(p)) for p in all_modules()}
    unknown = units - set(LAYER) - set(APPLICATION) - set(EDGES)
    assert not unknown, f"packages with no layer in tests/test_layers.py: {sorted(unknown)}"


def test_imports_go_one_way():
    problems = []
    for path in all_modules():
        importer = module_name(path)
        for imported in sorted(imported_modules(path)):
            why = violation(importer, imported)
            if why:
                problems.append(f"{path.relative_to(ROOT)} imports {imported}: {why}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("importer, imported, allowed", [
    ("visionpos.server.service", "bridge", False),
    ("visionpos.geometry.frames", "visionpos.fusion.tracking", False),
    ("visionpos.fusion.kernels", "visionpos.geometry.rotations", True),
    ("bridge.mavlink", "stations.agent", False),
    ("stations.sources", "visionpos.sim.render", True),
    ("visionpos.app.serve", "bridge", True),
    ("visionpos.app.demo", "visionpos.cli.main", False),
    ("visionpos.recording", "visionpos.server.ingest", False),
    ("console.server", "visionpos.server.service", True),
    ("console.view", "bridge.mavlink", False),
    ("console.health", "visionpos.app.serve", False),
    ("visionpos.server.service", "console.server", False),
    ("visionpos.app.console", "console.server", True),
    ("visionpos.benchmarks.robustness", "visionpos.app.demo", True),
    ("visionpos.benchmarks.sitl", "visionpos.app.sitl", True),
    ("visionpos.analysis.replay", "visionpos.benchmarks.fusion_replay", False),
    ("bridge.mavlink", "visionpos.benchmarks.factories", False),
])
def test_the_rules_themselves(importer, imported, allowed):
    assert (violation(importer, imported) is None) == allowed


def _cycles(package: str) -> list[list[str]]:
    """The import cycles among the modules of `package` (function-level imports count)."""
    graph = {module_name(p): set() for p in all_modules() if module_name(p).startswith(package)}
    for path in all_modules():
        name = module_name(path)
        if name in graph:
            graph[name] = {m for m in imported_modules(path) if m in graph and m != name}
    return cycles_of(graph)


def cycles_of(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node of {node: nodes it points to}, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.mark.parametrize("package", ["visionpos.benchmarks", "visionpos.app", "visionpos.calibration", "bridge"])
def test_no_import_cycles_inside(package):
    """Modules of these packages import one way among themselves too (a shared module where two need the
    same thing: benchmarks/fusion_replay.py for fusion.py and fusion_flights.py)."""
    assert _cycles(package) == []


def test_the_cycle_finder_itself():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d"}, "f": {"a"}, "g": set()}
    assert sorted(cycles_of(graph)) == [["a", "b", "c"], ["d", "e"]]
    assert cycles_of({"a": {"b"}, "b": set()}) == []


def test_a_station_loads_the_simulator_only_when_configured_to():
    """stations.sources imports visionpos.sim inside SimSource only (edge -> core is allowed, but a
    camera station that reads a real camera should not pay for loading the simulator)."""
    code = (
        "import sys, stations.agent, stations.sources as s\n"
        "from stations.config import SourceConfig\n"
        "s.make_source(SourceConfig(kind='images', path='.'))\n"
        "loaded = sorted(m for m in sys.modules if m.startswith('visionpos.sim'))\n"
        "assert not loaded, loaded\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


MAX_MODULE_LINES = 800  # a module longer than this holds several ideas: split it by concept (issue 26)


def test_no_module_is_longer_than_the_limit():
    long = {str(p.relative_to(ROOT)): n for p in all_modules()
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them by concept): {long}"
