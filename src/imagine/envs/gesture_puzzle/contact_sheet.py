"""A contact sheet of the task as the agent sees it: `imagine env show`.

Example scenes of goal, illegal and start macrostates with their labels, each beside the three
64 x 64 strips of its observation, and the fragment variation of one cube microstate and one
hand microstate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from imagine.checkpoint import save_figure
from imagine.envs.gesture_puzzle import rules
from imagine.envs.gesture_puzzle.scene import SceneComposer


def _examples(task: str, rng: np.random.Generator, per_kind: int) -> list[tuple[str, np.ndarray]]:
    s = rules.all_macrostates()
    kinds = {
        "goal": s[rules.is_goal(s, task)],
        "illegal": s[rules.is_illegal(s)],
        "start": rules.start_states(task),
    }
    return [
        (kind, pool[j])
        for kind, pool in kinds.items()
        for j in rng.choice(len(pool), size=per_kind, replace=False)
    ]


def _label(kind: str, state: np.ndarray, task: str) -> str:
    text = f"{kind}: {rules.describe(tuple(state))}"
    if kind == "start":
        text += f"  (optimal plan: {rules.optimal_plan_length(tuple(state), task)})"
    return text


def contact_sheet(
    composer: SceneComposer, task: str, seed: int, out: str | Path, per_kind: int = 2
) -> Path:
    """Write the contact sheet PNG to ``out`` and return its path."""
    rng = np.random.default_rng(seed)
    examples = _examples(task, rng, per_kind)
    pool = composer.pool
    n_rows = len(examples) + 2
    fig = Figure(figsize=(10, 1.9 * n_rows), layout="constrained")
    grid = fig.add_gridspec(n_rows, 4, width_ratios=[4.5, 1, 1, 1])
    for row, (kind, state) in enumerate(examples):
        frags = pool.sample_indices(rng, state)
        ax = fig.add_subplot(grid[row, 0])
        ax.imshow(composer.scene(state, frags), cmap="gray", vmin=0, vmax=255)
        ax.set_title(_label(kind, state, task), fontsize=10, loc="left")
        ax.axis("off")
        obs = composer.observe(state, frags)
        for c in range(rules.N_CUBES):
            ax = fig.add_subplot(grid[row, 1 + c])
            ax.imshow(obs[..., c], cmap="gray", vmin=0, vmax=255)
            ax.set_title(f"channel {c}", fontsize=8)
            ax.axis("off")

    cube, direction, hand = 0, rules.UP, 0
    cubes = pool.cubes[cube, direction, : pool.cube_counts[cube, direction]]
    hands = pool.hands[hand, : min(int(pool.hand_counts[hand]), 6)]
    ax = fig.add_subplot(grid[-2, :])
    ax.imshow(_tile(cubes, columns=8), cmap="gray", vmin=0, vmax=255)
    ax.set_title(
        f"all {len(cubes)} fragments of microstate (cube {cube}, "
        f"{rules.DIRECTION_NAMES[direction]})",
        fontsize=10,
        loc="left",
    )
    ax.axis("off")
    ax = fig.add_subplot(grid[-1, :])
    ax.imshow(_tile(hands, columns=2), cmap="gray", vmin=0, vmax=255)
    ax.set_title(
        f"{len(hands)} of {pool.hand_counts[hand]} fragments of microstate (hand points at cube "
        f"{hand})",
        fontsize=10,
        loc="left",
    )
    ax.axis("off")
    fig.suptitle(
        f"GesturePuzzle, task '{task}', seed {seed}: robot at the top, human at the bottom"
    )
    return save_figure(fig, out, dpi=80)


def _tile(images: np.ndarray, columns: int, gap: int = 4) -> np.ndarray:
    """Lay images (n, h, w) out in a grid with white gaps."""
    n, h, w = images.shape
    rows = -(-n // columns)
    sheet = np.full((rows * (h + gap) - gap, columns * (w + gap) - gap), 255, dtype=np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        sheet[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = img
    return sheet
