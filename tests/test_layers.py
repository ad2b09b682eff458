"""The package's layers (ARCHITECTURE.md): nothing imports upward, there are no import cycles, no trainer
imports another, and `verifiers/` (installed as `posttrain.verifiers`, the bottom layer) imports nothing of
posttrain outside itself, and no torch.

Read from the source with `ast` (every import statement, also those inside functions: a lazy import still
ties two modules together), so the check needs no imports of its own and runs in milliseconds.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Bottom to top. A module's unit is its first component under posttrain/ (posttrain.rollout.engine -> rollout).
LAYERS: list[set[str]] = [
    {"verifiers"},  # the repository's verifiers/ folder, installed as posttrain.verifiers (pyproject's package-dir)
    {"errors", "runtime", "trackers"},
    {"config"},
    {"data", "tasks", "chat", "models", "model_files", "model_card"},
    {"lean"},
    {"logprobs", "losses", "advantages"},
    {"rollout", "loop", "sharding"},
    {"scoring", "evaluation", "preferences", "problems", "plots"},
    {"trainers"},
    {"cli", "__main__", "__init__"},
]
LAYER_OF = {unit: i for i, units in enumerate(LAYERS) for unit in units}
# Packages of data files only (pyproject maps recipes/ to posttrain.recipes): nothing to import from.
DATA_PACKAGES = {"posttrain.recipes", "posttrain.recipes.launch"}
VERIFIERS = (ROOT / "verifiers", "posttrain.verifiers")


def module_files(package_dir: Path, name: str | None = None) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of the package at `package_dir` (a package's own name
    for its __init__.py), installed as `name` (default: the folder's name)."""
    base = package_dir.parent
    out = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if name:
            parts = name.split(".") + parts[1:]
        out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of `known` that `name` (at `path`) imports anywhere in its source, and every other top-level
    package it imports (as its bare name, e.g. "torch")."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found: set[str] = set()

    def add(target: str) -> None:
        if target in DATA_PACKAGES:
            return
        if target in known:
            found.add(target)
            return
        parent = target.rpartition(".")[0]
        if parent in known:
            found.add(parent)
        elif target.split(".")[0] == "posttrain":  # a posttrain module outside the graph: named in full
            found.add(target)
        else:
            found.add(target.split(".")[0])

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                module = ".".join(anchor + ([node.module] if node.module else []))
            else:
                module = node.module
            for alias in node.names:  # `from pkg import submodule` imports the submodule
                if f"{module}.{alias.name}" in known:
                    found.add(f"{module}.{alias.name}")
                else:
                    add(module)
    found.discard(name)
    return found


def import_graph(*packages: Path | tuple[Path, str]) -> dict[str, set[str]]:
    """The import graph of one or more packages (a folder, or (folder, installed name)) together."""
    files: dict[str, Path] = {}
    for pkg in packages:
        files.update(module_files(*pkg) if isinstance(pkg, tuple) else module_files(pkg))
    return {name: imports_of(name, path, set(files)) for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted; [] when acyclic."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"  # posttrain.verifiers.* -> "verifiers"


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Imports that run up a layer, of a unit no layer names, or from one trainer into another."""
    bad = []
    for src, targets in sorted(graph.items()):
        for dst in sorted(t for t in targets if t.startswith("posttrain")):
            us, ud = unit(src), unit(dst)
            if us not in LAYER_OF or ud not in LAYER_OF:
                bad.append(f"{src} -> {dst}: module {us if us not in LAYER_OF else ud!r} is in no layer "
                           "(add it to LAYERS in tests/test_layers.py and ARCHITECTURE.md)")
            elif LAYER_OF[ud] > LAYER_OF[us]:
                bad.append(f"{src} (layer {LAYER_OF[us]}: {us}) imports {dst} (layer {LAYER_OF[ud]}: {ud}), "
                           "which is above it")
            elif us == ud == "trainers" and src != "posttrain.trainers" and dst != "posttrain.trainers":
                bad.append(f"{src} imports another trainer, {dst}: move what they share into a shared module")
    return bad


def test_posttrain_layers_and_no_cycles():
    graph = import_graph(ROOT / "posttrain", VERIFIERS)
    assert "posttrain.trainers.grpo" in graph and "posttrain.lean.support" in graph
    assert "posttrain.verifiers.math_answer.verifier" in graph and "posttrain.verifiers.registry" in graph["posttrain.problems"]
    problems = layer_violations(graph) + [f"import cycle: {' <-> '.join(c)}" for c in cycles(graph)]
    assert not problems, "\n".join(problems)


def test_verifiers_import_nothing_of_posttrain_or_torch_and_have_no_cycles():
    graph = import_graph(VERIFIERS)
    assert "posttrain.verifiers.registry" in graph["posttrain.verifiers"]
    bad = [f"{m} imports {t}" for m, ts in sorted(graph.items()) for t in sorted(ts)
           if t == "torch" or t == "posttrain" or (t.startswith("posttrain.") and t not in graph)]
    bad += [f"import cycle: {' <-> '.join(c)}" for c in cycles(graph)]
    assert not bad, "\n".join(bad)


MAX_FLOORS = 8  # issue 50: a ninth floor (scoring -> preferences) was taken down by moving the pair rows to data


def room(module: str) -> str:
    """A module's room in the floor count: a package folder under posttrain/ (rollout, trainers, tasks, lean) is one
    room, any other module its own."""
    parts = module.split(".")
    return ".".join(parts[:2])


def floors(graph: dict[str, set[str]]) -> list[str]:
    """The longest chain of imports between posttrain's rooms, top room first (its length is the number of floors;
    `posttrain.verifiers`, the package below them all, and the package's own __init__ are not counted)."""
    rooms: dict[str, set[str]] = {}
    for src, targets in graph.items():
        if src == "posttrain" or src.startswith("posttrain.verifiers"):
            continue
        rooms.setdefault(room(src), set()).update(
            room(t) for t in targets if t.startswith("posttrain.") and not t.startswith("posttrain.verifiers")
            and room(t) != room(src))
    memo: dict[str, list[str]] = {}

    def chain(r: str) -> list[str]:
        if r not in memo:
            memo[r] = [r] + max((chain(t) for t in rooms.get(r, ()) if t in rooms), key=len, default=[])
        return memo[r]

    return max((chain(r) for r in sorted(rooms)), key=len)


def test_the_import_graph_has_at_most_eight_floors():
    graph = import_graph(ROOT / "posttrain", VERIFIERS)
    assert not cycles(graph)
    longest = floors(graph)
    assert len(longest) <= MAX_FLOORS, (f"{len(longest)} floors of imports (at most {MAX_FLOORS}): "
                                        + " -> ".join(longest))


# ------------------------------------------------------------------ the checker itself
def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "posttrain"
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


def test_checker_reports_a_cycle_an_upward_import_and_trainer_to_trainer(tmp_path):
    root = _package(tmp_path, {
        "__init__.py": "",
        "models.py": "from posttrain import chat\n",
        "chat.py": "def f():\n    from posttrain.models import x\n",  # lazy import: still a cycle
        "config.py": "from posttrain.loop import setup\n",  # config (1) -> loop (5): upward
        "loop.py": "",
        "rollout/__init__.py": "from .engine import generate\n",
        "rollout/engine.py": "from ..models import unwrap_model\nimport torch\n",
        "trainers/__init__.py": "",
        "trainers/ppo.py": "from posttrain.trainers.reward import load\n",
        "trainers/reward.py": "",
    })
    graph = import_graph(root)
    assert graph["posttrain.rollout"] == {"posttrain.rollout.engine"}
    assert graph["posttrain.rollout.engine"] == {"posttrain.models", "torch"}
    assert cycles(graph) == [["posttrain.chat", "posttrain.models"]]
    bad = layer_violations(graph)
    assert any("posttrain.config" in b and "above it" in b for b in bad)
    assert any("another trainer" in b for b in bad)
    assert len(bad) == 2


@pytest.mark.parametrize("stmt, expected", [
    ("from . import records\n", {"posttrain.rollout.records"}),
    ("from .records import Rollout\n", {"posttrain.rollout.records"}),
    ("from .. import models\n", {"posttrain.models"}),
    ("import posttrain.rollout.records as r\n", {"posttrain.rollout.records"}),
    ("from posttrain import rollout\n", {"posttrain.rollout"}),
])
def test_checker_resolves_relative_and_submodule_imports(tmp_path, stmt, expected):
    root = _package(tmp_path, {"__init__.py": "", "models.py": "", "rollout/__init__.py": "",
                               "rollout/records.py": "", "rollout/engine.py": stmt})
    assert import_graph(root)["posttrain.rollout.engine"] == expected


def test_checker_maps_the_verifiers_folder_to_its_installed_name(tmp_path):
    """verifiers/ is installed as posttrain.verifiers: its own imports resolve inside it, one of the rest of
    posttrain is named in full (and so reported), and a posttrain module importing it sees the bottom layer."""
    folder = tmp_path / "verifiers"
    (folder / "math_answer").mkdir(parents=True)
    (folder / "__init__.py").write_text("from posttrain.verifiers.registry import get\n")
    (folder / "registry.py").write_text("from posttrain.config import load\nfrom . import math_answer\n")
    (folder / "math_answer" / "__init__.py").write_text("import sympy\n")
    graph = import_graph((folder, "posttrain.verifiers"))
    assert graph["posttrain.verifiers"] == {"posttrain.verifiers.registry"}
    assert graph["posttrain.verifiers.registry"] == {"posttrain.config", "posttrain.verifiers.math_answer"}
    assert graph["posttrain.verifiers.math_answer"] == {"sympy"}
    root = _package(tmp_path, {"__init__.py": "", "problems.py": "from posttrain.verifiers import get\n",
                               "errors.py": ""})
    both = import_graph(root, (folder, "posttrain.verifiers"))
    assert both["posttrain.problems"] == {"posttrain.verifiers"}
    assert not [b for b in layer_violations(both) if "posttrain.problems" in b]


def test_floors_count_a_package_folder_as_one_room(tmp_path):
    root = _package(tmp_path, {
        "__init__.py": "from posttrain import cli\n",  # the package's own __init__: not a room
        "cli.py": "from posttrain.trainers import sft\n",
        "trainers/__init__.py": "",
        "trainers/sft.py": "from posttrain.trainers import common\nfrom posttrain import loop\n",  # inside one room
        "trainers/common.py": "from posttrain import loop\n",
        "loop.py": "from posttrain import errors\nfrom posttrain.verifiers import registry\n",
        "errors.py": "",
    })
    assert floors(import_graph(root)) == ["posttrain.cli", "posttrain.trainers", "posttrain.loop", "posttrain.errors"]
