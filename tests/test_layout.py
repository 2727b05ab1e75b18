"""The package's layers (docs/design.md section 5): imports only point down, and nothing imports in
a cycle, function-level imports included.

Layers, bottom up: the leaves (config, errors, checkpoint, metrics, ...); ``envs`` (the env spec,
any Gymnasium env, GesturePuzzle's environment); ``models`` (V, M, C); ``learning`` (Algorithm
1); ``study`` (experiments and reports); ``cli``. GesturePuzzle's extras live in its own package
but each sits on the layer of what it uses (its encoders and true model on ``models``', its
evaluation and V report on ``learning``'s), so the core reaches them only through the env spec.
"""

import ast
from pathlib import Path

import imagine

PACKAGE = Path(imagine.__file__).parent

LAYER = {"envs": 1, "models": 2, "learning": 3, "study": 4, "cli": 5}
"""Each module's layer is its package's; leaves (top-level modules) are 0."""

GESTURE_PUZZLE_EXTRAS = {
    "imagine.envs.gesture_puzzle.encoders": 2,
    "imagine.envs.gesture_puzzle.true_model": 2,
    "imagine.envs.gesture_puzzle.evaluation": 3,
    "imagine.envs.gesture_puzzle.vision_report": 3,
    "imagine.envs.gesture_puzzle.extras": 3,
    "imagine.envs.classic_control.true_model": 2,
    "imagine.envs.classic_control.extras": 3,
}
"""GesturePuzzle modules above the env layer: the probes of a trained V, M or C."""


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int:
    if module in GESTURE_PUZZLE_EXTRAS:
        return GESTURE_PUZZLE_EXTRAS[module]
    parts = module.split(".")
    return LAYER.get(parts[1], 0) if len(parts) > 1 else 0


def is_module(name: str) -> bool:
    """Whether a dotted name is a module or package of imagine (not a name inside one)."""
    path = PACKAGE.parent / name.replace(".", "/")
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imports() -> dict[str, set[str]]:
    """Every module's imports of other imagine modules, wherever in the file they are."""
    graph = {}
    for path in PACKAGE.rglob("*.py"):
        name = module_name(path)
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for a in node.names:  # `from P import m` of a submodule m imports P.m
                    sub = f"{node.module}.{a.name}"
                    found.add(sub if is_module(sub) else node.module)
            elif isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
        graph[name] = {m for m in found if m.startswith("imagine")}
    modules = set(graph)
    return {k: {m for m in v if m in modules and m not in ("imagine", k)} for k, v in graph.items()}


def test_imports_only_point_down():
    upward = [
        f"{module} (layer {layer(module)}) imports {other} (layer {layer(other)})"
        for module, others in imports().items()
        for other in others
        if layer(other) > layer(module)
    ]
    assert upward == []


def test_no_module_imports_in_a_cycle():
    graph = imports()
    state: dict[str, int] = {}

    def visit(module: str, path: list[str]) -> list[str] | None:
        state[module] = 1
        for other in sorted(graph[module]):
            if state.get(other) == 1:
                return [*path, module, other]
            if other not in state and (cycle := visit(other, [*path, module])):
                return cycle
        state[module] = 2
        return None

    cycles = [c for m in sorted(graph) if m not in state and (c := visit(m, []))]
    assert cycles == []


def test_the_core_imports_no_gesture_puzzle_module():
    """models and learning reach GesturePuzzle only through its spec and its extras, named by
    entry-point strings (imagine.EXTRAS, as Gymnasium names environments)."""
    core = [
        f"{module} imports {other}"
        for module, others in imports().items()
        if layer(module) in (2, 3) and ".gesture_puzzle" not in module
        for other in others
        if ".gesture_puzzle" in other
    ]
    # V's training reads GesturePuzzle's dataset and fits its latent classifier (both on the
    # env layer, below models); nothing else
    allowed = {f"imagine.models.vision_training imports imagine.envs.gesture_puzzle.{m}"
               for m in ("dataset", "latent_classifier")}  # fmt: skip
    assert set(core) <= allowed
