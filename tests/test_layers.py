"""No import points up the layers (design.md): envs -> policies -> data -> encoders/worldmodel/wam ->
planning -> evaluation -> command-line. Every import in src/wamplan counts, lazy ones inside functions too.
Run as a script (``python tests/test_layers.py``) it prints the import map between layers."""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "wamplan"

# the shared helpers every layer may use (configs, registries, errors, checkpoints, the training loop, progress bars)
FOUNDATION = {"wamplan", "wamplan.errors", "wamplan.config", "wamplan.registry", "wamplan.device", "wamplan.optim",
              "wamplan.parallel", "wamplan.provenance", "wamplan.checkpoint", "wamplan.train_loop", "wamplan.plot",
              "wamplan.progress"}
LAYERS = {"envs": 1, "policies": 2, "data": 3, "encoders": 4, "worldmodel": 4, "wam": 4, "planning": 5,
          "evaluation": 6, "presets": 6}
CLI = 7  # wamplan.cli, wamplan.plot_commands and every <concept>/commands.py
NAMES = {0: "foundation", 1: "envs", 2: "policies", 3: "data", 4: "encoders/worldmodel/wam", 5: "planning",
         6: "evaluation", 7: "cli/commands"}


def layer(module: str) -> int:
    if module in ("wamplan.cli", "wamplan.plot_commands") or module.endswith(".commands"):
        return CLI
    if module in FOUNDATION:
        return 0
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in LAYERS:
        raise AssertionError(f"{module} is in no layer; add it to tests/test_layers.py")
    return LAYERS[parts[1]]


def module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports() -> dict[str, set[str]]:
    """module -> the wamplan modules it imports (``from wamplan.x import y`` counts as wamplan.x)."""
    return {module_name(path): _wamplan_imports(path) for path in sorted(SRC.rglob("*.py"))}


def _wamplan_imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
            [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else []
        out.update(n for n in names if n == "wamplan" or n.startswith("wamplan."))
    return out


def test_no_import_points_up_the_layers():
    upward = [f"{m} ({NAMES[layer(m)]}) imports {t} ({NAMES[layer(t)]})"
              for m, targets in imports().items() for t in sorted(targets) if layer(t) > layer(m)]
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_nothing_imports_a_command_module():
    tests = {f"tests.{p.stem}": _wamplan_imports(p) for p in sorted(Path(__file__).parent.glob("*.py"))}
    users = [f"{m} imports {t}" for m, targets in {**imports(), **tests}.items() for t in targets
             if layer(t) == CLI and t != "wamplan.cli"]
    assert not users, "command modules are entry points, not libraries:\n" + "\n".join(users)


def test_the_task_contract_is_imported_from_envs_only():
    moved = {"CAMERAS", "ACTION_DIM", "PROPRIO_DIM", "Observation", "STAGES", "OUTCOMES"}
    wrong = []
    for path in sorted([*SRC.rglob("*.py"), *SRC.parents[1].joinpath("tests").glob("*.py"),
                        *SRC.parents[1].joinpath("benchmarks").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("wamplan.") and \
                    node.module != "wamplan.envs.contract" and node.module != "wamplan.envs":
                wrong += [f"{path.name}: {a.name} from {node.module}" for a in node.names if a.name in moved]
    assert not wrong, "import the task's contract from wamplan.envs.contract:\n" + "\n".join(wrong)


if __name__ == "__main__":
    by_layer: dict[str, set[str]] = defaultdict(set)
    for m, targets in imports().items():
        for t in targets:
            if layer(t) != layer(m) or m.split(".")[:2] != t.split(".")[:2]:
                by_layer[m].add(t)
    for m in sorted(by_layer, key=lambda m: (layer(m), m)):
        print(f"[{NAMES[layer(m)]}] {m} -> {', '.join(sorted(by_layer[m]))}")
    sys.exit(0)
