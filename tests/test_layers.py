"""The layers of docs/design.md, checked on the code: envs -> policies -> data -> encoders/worldmodel/wam ->
planning -> evaluation -> api -> cli. An import may only point down (or stay in its folder), between
modules and between folders, and no modules import each other in a circle; the cube task's own modules
(``ENV_ONLY``) are read by the env layer alone, every layer above it takes a task spec. Every import in
src/wamplan counts, lazy ones inside functions too. Run as a script (``python tests/test_layers.py``) it prints
the map between layers, the upward imports, the circles (modules and folders) and the reads of the cube task's
modules above the env layer."""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "wamplan"

# the shared helpers every layer may use (configs, registries, errors, checkpoints, the training loop, progress bars,
# the HTTP plumbing of both servers)
FOUNDATION = {"wamplan", "wamplan.errors", "wamplan.config", "wamplan.registry", "wamplan.device", "wamplan.optim",
              "wamplan.parallel", "wamplan.provenance", "wamplan.checkpoint", "wamplan.train_loop",
              "wamplan.train_config", "wamplan.train_log", "wamplan.plot", "wamplan.progress", "wamplan.locks",
              "wamplan.serving", "wamplan.serving.refusals", "wamplan.serving.runner"}
LAYERS = {"envs": 1, "policies": 2, "data": 3, "encoders": 4, "worldmodel": 4, "wam": 4, "planning": 5,
          "evaluation": 6, "presets": 6, "proxy": 6, "api": 7, "cli": 8}
NAMES = {0: "foundation", 1: "envs", 2: "policies", 3: "data", 4: "encoders/worldmodel/wam", 5: "planning",
         6: "evaluation", 7: "api", 8: "cli"}
# the package's face re-exports the API lazily (PEP 562 __getattr__), so it counts as the API layer's for its imports
FACE = "wamplan"
# the cube task's constants and its ManiSkill env: only modules in envs/ may import them (the others read a TaskSpec)
ENV_ONLY = ("wamplan.envs.contract", "wamplan.envs.task")


def layer(module: str) -> int:
    if module in FOUNDATION:
        return 0
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in LAYERS:
        raise AssertionError(f"{module} is in no layer; add it to tests/test_layers.py")
    return LAYERS[parts[1]]


def folder(module: str) -> str:
    """The top-level concept a module belongs to: ``wamplan.planning.policy`` -> ``planning``."""
    parts = module.split(".")
    return "foundation" if module in FOUNDATION else parts[1]


def module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports() -> dict[str, set[str]]:
    """module -> the wamplan modules it imports (``from wamplan.x import y`` counts as wamplan.x, or as
    wamplan.x.y where that is a module)."""
    known = {module_name(p) for p in SRC.rglob("*.py")}
    return {module_name(path): _wamplan_imports(path, known) for path in sorted(SRC.rglob("*.py"))}


def _wamplan_imports(path: Path, known: set[str] | None = None) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            sub = [f"{node.module}.{a.name}" for a in node.names]
            names = [node.module, *(s for s in sub if known and s in known)]
        else:
            names = []
        out.update(n for n in names if n == "wamplan" or n.startswith("wamplan."))
    return out


def _edges() -> list[tuple[str, str]]:
    return [(m, t) for m, targets in imports().items() if m != FACE for t in sorted(targets)
            if t != m and t != FACE and not m.startswith(t + ".")]  # a package's own __init__ is not an edge


def upward_modules() -> list[str]:
    return [f"{m} ({NAMES[layer(m)]}) imports {t} ({NAMES[layer(t)]})" for m, t in _edges() if layer(t) > layer(m)]


def upward_folders() -> list[str]:
    """Folder pairs whose imports point up, or both ways (then the two folders cannot be in distinct layers)."""
    pairs = {(folder(m), folder(t)) for m, t in _edges() if folder(m) != folder(t)}
    both = sorted({tuple(sorted(p)) for p in pairs if (p[1], p[0]) in pairs})
    order = {f: (0 if f == "foundation" else LAYERS[f]) for pair in pairs for f in pair}
    up = sorted(f"{a} imports {b}" for a, b in pairs if order[b] > order[a])
    return up + [f"{a} and {b} import each other" for a, b in both]


def circles() -> list[list[str]]:
    """The module import graph's strongly connected components of more than one module (Tarjan)."""
    graph: dict[str, set[str]] = defaultdict(set)
    for m, t in _edges():
        graph[m].add(t)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def task_internals_above_envs() -> list[str]:
    """Imports of the cube task's own modules (``ENV_ONLY``) from outside envs/, the package's face included."""
    return [f"{m} imports {t}" for m, targets in imports().items() if folder(m) != "envs"
            for t in sorted(targets) if t in ENV_ONLY]


def test_no_import_points_up_the_layers():
    up = upward_modules()
    assert not up, "upward imports:\n" + "\n".join(up)


def test_folders_sit_where_their_imports_say():
    up = upward_folders()
    assert not up, "folders whose imports run up or both ways:\n" + "\n".join(up)


def test_no_modules_import_each_other_in_a_circle():
    found = circles()
    assert not found, "import circles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_nothing_below_the_cli_imports_it():
    users = [f"{m} imports {t}" for m, t in _edges() if folder(t) == "cli" and folder(m) != "cli"]
    assert not users, "the command line is an entry point, not a library:\n" + "\n".join(users)


def test_only_the_env_layer_reads_the_cube_tasks_modules():
    found = task_internals_above_envs()
    assert not found, ("modules above envs/ take the task from a TaskSpec (env.task, a store's or checkpoint's "
                       "task), not from the cube task's modules:\n" + "\n".join(found))


def test_task_names_are_imported_from_their_home():
    """The cube's constants come from wamplan.envs.contract (tests and benchmarks may read them), the task types from
    wamplan.envs.spec (or the envs package, or the contract that re-exports them), never through another module."""
    constants = ("CAMERAS", "ACTION_DIM", "PROPRIO_DIM", "STAGES", "OUTCOMES")
    homes = {name: ("wamplan.envs.contract",) for name in constants}
    homes.update({name: ("wamplan.envs.spec", "wamplan.envs", "wamplan.envs.contract")
                  for name in ("Observation", "TaskSpec")})
    wrong = []
    for path in sorted([*SRC.rglob("*.py"), *SRC.parents[1].joinpath("tests").glob("*.py"),
                        *SRC.parents[1].joinpath("benchmarks").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("wamplan."):
                wrong += [f"{path.name}: {a.name} from {node.module} (its home: {homes[a.name][0]})"
                          for a in node.names if a.name in homes and node.module not in homes[a.name]]
    assert not wrong, "import the task's names from their home:\n" + "\n".join(wrong)


if __name__ == "__main__":
    by_layer: dict[str, set[str]] = defaultdict(set)
    for m, t in _edges():
        if folder(m) != folder(t):
            by_layer[m].add(t)
    for m in sorted(by_layer, key=lambda m: (layer(m), m)):
        print(f"[{NAMES[layer(m)]}] {m} -> {', '.join(sorted(by_layer[m]))}")
    up, fup, circ, cube = upward_modules(), upward_folders(), circles(), task_internals_above_envs()
    print(f"\nupward imports between modules: {len(up)}", *up, sep="\n  ")
    print(f"folders importing up or both ways: {len(fup)}", *fup, sep="\n  ")
    print(f"circles of modules: {len(circ)}", *(" <-> ".join(c) for c in circ), sep="\n  ")
    print(f"the cube task's modules read above envs/: {len(cube)}", *cube, sep="\n  ")
    sys.exit(0)
