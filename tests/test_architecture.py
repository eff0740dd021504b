"""The house drawn from the imports: no cycles, and the runtime never enters the design wing.

The graph is built from the source (every ``import`` statement, at module level and inside
functions alike; ``if TYPE_CHECKING:`` blocks excepted, they never run). An edge goes to the
module an import names: ``from mrft_gcs.identify import identify`` is an edge to the package
``mrft_gcs.identify`` (its ``__init__``), ``from mrft_gcs import _kernels`` to the submodule.
A package's ``__init__`` importing its own submodules is how a package exposes them, so the
implicit import of a parent package is not an edge (it would make every package a cycle).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import mrft_gcs

PKG = Path(mrft_gcs.__file__).resolve().parent
#: the offline design pipeline (discretise, phase, side design, dataset, train, evaluate)
DESIGN = "mrft_gcs.design"
#: runtime modules allowed to import the design wing, lazily inside the command they serve
DESIGN_GATES = {"mrft_gcs.cli.design"}
HEAVY_DESIGN_DEPS = ("torch", "onnx", "distributed", "dask")


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import/ImportFrom node, skipping ``if TYPE_CHECKING:`` bodies."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """``(internal, external)``: per module, the mrft_gcs modules and the top-level
    third-party names it imports."""
    mods = _modules()
    internal: dict[str, set[str]] = {m: set() for m in mods}
    external: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
                for name in names:
                    if name.split(".")[0] == "mrft_gcs":
                        # `import a.b.c` binds and runs a.b.c; take the longest known prefix
                        parts = name.split(".")
                        while ".".join(parts) not in mods:
                            parts.pop()
                        internal[mod].add(".".join(parts))
                    else:
                        external[mod].add(name.split(".")[0])
                continue
            base = node.module or ""
            if node.level:
                anchor = mod.split(".") if is_pkg else mod.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            if base.split(".")[0] != "mrft_gcs":
                if base != "__future__":
                    external[mod].add(base.split(".")[0])
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                internal[mod].add(sub if sub in mods else base)
    for mod in internal:
        internal[mod].discard(mod)
    return internal, external


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

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


def _in_design(mod: str) -> bool:
    return mod == DESIGN or mod.startswith(DESIGN + ".")


def test_the_graph_sees_imports_inside_functions():
    internal, _ = import_graph()
    # cli/design.py imports the design wing only inside its commands
    assert any(_in_design(m) for m in internal["mrft_gcs.cli.design"])
    assert "mrft_gcs.identify" in internal["mrft_gcs.flight.api"]


def test_the_cycle_finder_finds_cycles():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(g) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    internal, _ = import_graph()
    cycles = _cycles(internal)
    assert not cycles, "import cycles (strongly connected modules): " + "; ".join(
        " <-> ".join(c) for c in cycles)


def test_the_design_wing_is_a_subpackage():
    internal, _ = import_graph()
    wing = {m for m in internal if _in_design(m)}
    for name in ("discretize", "phase", "side", "dataset", "train", "evaluate", "pipeline"):
        assert f"{DESIGN}.{name}" in wing, f"{DESIGN}.{name} missing"


def test_runtime_never_imports_the_design_wing_or_torch():
    internal, external = import_graph()
    bad = []
    for mod, deps in internal.items():
        if _in_design(mod) or mod in DESIGN_GATES:
            continue
        bad += [f"{mod} -> {d}" for d in sorted(deps) if _in_design(d)]
        bad += [f"{mod} -> {d}" for d in sorted(external[mod]) if d in HEAVY_DESIGN_DEPS]
    assert not bad, "runtime modules import the design wing: " + ", ".join(bad)


#: the tuning sequence's rooms, one per phase (:mod:`mrft_gcs.flight.phases`)
SEQUENCE = "mrft_gcs.flight.sequence"
PHASES = "mrft_gcs.flight.phases"


def test_the_sequence_is_split_by_phase_and_the_phases_stand_below_it():
    """One module per phase; the sequence composes them; no phase reaches back up into the
    sequence or the driver that runs it (they share state only through ``phases.shared``)."""
    internal, _ = import_graph()
    rooms = {m for m in internal if m.startswith(PHASES + ".")}
    for name in ("state", "shared", "liftoff", "altitude", "attitude", "side"):
        assert f"{PHASES}.{name}" in rooms, f"{PHASES}.{name} missing"
        assert f"{PHASES}.{name}" in internal[SEQUENCE], f"the sequence skips {name}"
    up = {SEQUENCE, "mrft_gcs.flight.driver", "mrft_gcs.flight.api", "mrft_gcs.flight"}
    bad = [f"{m} -> {d}" for m in sorted(rooms) for d in sorted(internal[m] & up)]
    assert not bad, "phases import the sequence or its drivers: " + ", ".join(bad)


_PROBE = """
import json, sys
import numpy as np
import mrft_gcs.cli
mrft_gcs.cli._register()  # every command module, as `mrft-tune` loads them
from mrft_gcs.identify.live import warm_up_identification
from mrft_gcs.identify import identify, relay_settings
from mrft_gcs.loops import LoopKind
warm_up_identification(relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE))
rec = np.load(sys.argv[1])
roll = identify(LoopKind.ATTITUDE, rec["roll_t"], rec["roll_u"], rec["roll_y"],
                beta=float(rec["roll_beta"]), h=float(rec["roll_h"]))
side = identify(LoopKind.SIDE, rec["t"], rec["u"], rec["y"], beta=float(rec["beta"]),
                h=float(rec["h"]), inner=roll, setpoint=float(rec["setpoint"]), tilt=rec["tilt"])
print(json.dumps({"gains": [side.gains.Kc, side.gains.Kd], "modules": sorted(sys.modules)}))
"""


def test_identification_at_run_time_loads_no_design_module_and_no_torch():
    rec = Path(__file__).parent / "data" / "racer250_y_stalled_cycles.npz"
    out = subprocess.run([sys.executable, "-c", _PROBE, str(rec)], capture_output=True,
                         text=True, timeout=120, check=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(g > 0 for g in res["gains"])  # the side loop was really identified
    loaded = res["modules"]
    assert "mrft_gcs.identify.runtime" in loaded
    design = [m for m in loaded if _in_design(m)]
    heavy = [m for m in loaded if m.split(".")[0] in HEAVY_DESIGN_DEPS]
    assert not design and not heavy, (design, heavy)
