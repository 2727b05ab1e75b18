"""The GesturePuzzle state machine (docs/design.md section 1; paper section V-A).

A macrostate is ``(d0, d1, d2, h)``: ``d_i`` in {UP=0, RIGHT=1, DOWN=2, LEFT=3} is the arrow on
cube i (cubes left to right, the robot at the top of the image, the human at the bottom, so DOWN
points toward the human), and ``h`` in {0, 1, 2} is the cube the human's hand points at.
4^3 x 3 = 192 macrostates.

Action ``a = 2*i + k`` rotates cube ``i`` by 90 degrees: clockwise for ``k = 0``
(``d -> (d + 1) % 4``), counter-clockwise for ``k = 1`` (``d -> (d - 1) % 4``). In the paper's
task the hand never moves within an episode; with a *stochastic human* (``hand_switch_prob``
p > 0, issue 16) it moves after each action, with probability p, to one of the other two cubes
(each p / 2); the reward and the episode's end are those of the state after the hand moved.

Everything here is pure and works on plain tuples or on integer arrays of shape (..., 4), so the
single and the vectorized environment share one definition of the rules.
"""

from __future__ import annotations

from collections import deque
from functools import cache
from typing import Literal

import numpy as np

from imagine.config import TASKS

UP, RIGHT, DOWN, LEFT = 0, 1, 2, 3
DIRECTION_NAMES = ("up", "right", "down", "left")
DIRECTION_ARROWS = ("↑", "→", "↓", "←")
N_CUBES = 3
N_DIRECTIONS = 4
N_ACTIONS = 2 * N_CUBES
N_MACROSTATES = N_DIRECTIONS**N_CUBES * N_CUBES  # 192

REWARD_GOAL = 50.0
REWARD_ILLEGAL = -5.0
REWARD_STEP = -1.0
MAX_EPISODE_ACTIONS = 10

Task = Literal["original", "hard"]

Macrostate = tuple[int, int, int, int]


def check_task(task: str) -> str:
    """Return ``task`` if it is a known task, else raise a ValueError naming the choices."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASKS)}")
    return task


def check_action(action: object) -> int:
    """Return ``action`` as an int in [0, 6), else raise a ValueError that says what is wrong."""
    if isinstance(action, np.ndarray) and action.shape == ():
        action = action.item()
    if isinstance(action, bool) or not isinstance(action, int | np.integer):
        raise ValueError(f"invalid action {action!r}: expected an integer in 0..{N_ACTIONS - 1}")
    if not 0 <= int(action) < N_ACTIONS:
        raise ValueError(f"invalid action {int(action)}: expected an integer in 0..{N_ACTIONS - 1}")
    return int(action)


# --- The rules on arrays of macrostates, shape (..., 4) ---------------------------------------


def is_illegal(states: np.ndarray) -> np.ndarray:
    """True where two arrows share a direction."""
    d = np.asarray(states)[..., :N_CUBES]
    return (d[..., 0] == d[..., 1]) | (d[..., 0] == d[..., 2]) | (d[..., 1] == d[..., 2])


def is_goal(states: np.ndarray, task: str) -> np.ndarray:
    """True in goal states: legal and the pointed cube's arrow faces the human (``d_h == DOWN``);
    task ``hard`` additionally requires that no arrow faces the robot (no UP)."""
    s = np.asarray(states)
    d, h = s[..., :N_CUBES], s[..., N_CUBES]
    pointed = np.take_along_axis(d, h[..., None], axis=-1)[..., 0]
    goal = ~is_illegal(s) & (pointed == DOWN)
    if check_task(task) == "hard":
        goal &= ~(d == UP).any(axis=-1)
    return goal


def is_terminal(states: np.ndarray, task: str) -> np.ndarray:
    """Terminal states end an episode: goal or illegal."""
    return is_goal(states, task) | is_illegal(states)


def apply_actions(states: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The transition function: rotate cube ``a // 2`` clockwise (``a % 2 == 0``) or
    counter-clockwise (``a % 2 == 1``). Returns new states; the hand ``h`` is unchanged."""
    s = np.array(states, dtype=np.int64, copy=True)
    a = np.asarray(actions, dtype=np.int64)
    cube, turn = a // 2, np.where(a % 2 == 0, 1, -1)
    rotated = (np.take_along_axis(s, cube[..., None], axis=-1)[..., 0] + turn) % N_DIRECTIONS
    np.put_along_axis(s, cube[..., None], rotated[..., None], axis=-1)
    return s


def check_hand_switch_prob(p: float) -> float:
    """Return ``p`` if it is a probability, else raise a ValueError."""
    if isinstance(p, bool) or not isinstance(p, int | float) or not 0.0 <= p <= 1.0:
        raise ValueError(f"hand_switch_prob must be a probability in [0, 1], got {p!r}")
    return float(p)


def move_hand(state: np.ndarray, p: float, rng: np.random.Generator) -> np.ndarray:
    """The stochastic human after an action: with probability ``p`` the hand of ``state`` (4,)
    moves to one of the other two cubes, each equally likely (one uniform draw from ``rng``
    and, if it moves, one integer). With ``p == 0`` nothing is drawn: the paper's task has the
    random streams it has without this option."""
    if p == 0.0 or rng.random() >= p:
        return state
    moved = np.array(state, dtype=np.int64, copy=True)
    moved[N_CUBES] = (moved[N_CUBES] + 1 + rng.integers(N_CUBES - 1)) % N_CUBES
    return moved


def next_state_distribution(state: Macrostate, action: int, p: float) -> dict[Macrostate, float]:
    """The exact distribution of the next macrostate after ``action`` in ``state`` with
    ``hand_switch_prob`` p: the rotated state with its hand kept (1 - p) or moved to each other
    cube (p / 2 each)."""
    d0, d1, d2, h = transition(state, action)
    out = {(d0, d1, d2, h): 1.0 - p}
    for other in range(N_CUBES):
        if other != h and p > 0:
            out[(d0, d1, d2, other)] = p / (N_CUBES - 1)
    return out


def rewards(next_states: np.ndarray, task: str) -> np.ndarray:
    """+50 on entering a goal state, -5 on entering an illegal state, -1 otherwise."""
    return np.where(
        is_goal(next_states, task),
        REWARD_GOAL,
        np.where(is_illegal(next_states), REWARD_ILLEGAL, REWARD_STEP),
    )


# --- Tuple forms and enumerations ----------------------------------------------------------------


def transition(state: Macrostate, action: int) -> Macrostate:
    """The ground-truth next macrostate for one ``(state, action)``."""
    return tuple(int(x) for x in apply_actions(np.asarray(state), np.asarray(check_action(action))))  # type: ignore[return-value]


@cache
def all_macrostates() -> np.ndarray:
    """All 192 macrostates as an int64 array of shape (192, 4), in index order."""
    d = np.indices((N_DIRECTIONS,) * N_CUBES + (N_CUBES,)).reshape(N_CUBES + 1, -1).T
    out = np.ascontiguousarray(d, dtype=np.int64)
    out.setflags(write=False)
    return out


def macrostate_index(states: np.ndarray) -> np.ndarray:
    """Index of each macrostate in :func:`all_macrostates` (shape (...,))."""
    s = np.asarray(states, dtype=np.int64)
    return ((s[..., 0] * 4 + s[..., 1]) * 4 + s[..., 2]) * 3 + s[..., 3]


@cache
def start_states(task: str) -> np.ndarray:
    """The states an episode can start in: legal and not goal (54 for original, 66 for hard)."""
    s = all_macrostates()
    out = s[~is_terminal(s, task)]
    out.setflags(write=False)
    return out


@cache
def _optimal_lengths(task: str) -> dict[Macrostate, int]:
    """Breadth-first search backwards from the goal states through legal states."""
    states = [tuple(int(x) for x in s) for s in all_macrostates()]
    goal = {s for s, g in zip(states, is_goal(all_macrostates(), task), strict=True) if g}
    illegal = {s for s, b in zip(states, is_illegal(all_macrostates()), strict=True) if b}
    dist: dict[Macrostate, int] = {g: 0 for g in goal}
    frontier = deque(goal)
    while frontier:
        s = frontier.popleft()
        # Rotations are invertible: predecessors of s are its neighbours under any action.
        for a in range(N_ACTIONS):
            p = transition(s, a)
            if p not in dist and p not in illegal and p not in goal:
                dist[p] = dist[s] + 1
                frontier.append(p)
    return dist


def optimal_plan_length(state: Macrostate, task: str) -> int | None:
    """Fewest actions that take ``state`` to a goal state without passing an illegal state.

    0 for a goal state; ``None`` for an illegal state or where no legal path exists.
    """
    return _optimal_lengths(check_task(task)).get(tuple(int(x) for x in state))  # type: ignore[arg-type]


def best_success(
    task: str, p: float = 0.0, horizon: int = MAX_EPISODE_ACTIONS
) -> tuple[float, np.ndarray]:
    """The most any policy can succeed with a stochastic human p: the probability of entering a
    goal state within ``horizon`` actions, averaged over the uniformly drawn start states, by
    backward induction over :func:`next_state_distribution`:
    W_k(s) = max_a sum_s' P(s' | s, a) [goal(s') + live(s') W_{k-1}(s')], W_0 = 0, where live
    means neither goal nor illegal. Returns that mean and the best action with k actions left,
    ``actions[k - 1, macrostate_index(s)]`` (shape (horizon, 192)). 1.0 at p = 0 (every start
    state is at most a few legal actions from a goal); below 1 for p > 0, where the hand's
    moves can keep an agent from reaching a goal within the 10 actions."""
    check_task(task)
    states = all_macrostates()
    rotated = apply_actions(np.repeat(states, N_ACTIONS, axis=0),
                            np.tile(np.arange(N_ACTIONS), len(states)))  # fmt: skip
    outcomes, weights = [], []
    for shift in range(N_CUBES):  # the hand kept (shift 0) or moved to another cube
        moved = rotated.copy()
        moved[:, 3] = (moved[:, 3] + shift) % N_CUBES
        outcomes.append(macrostate_index(moved).reshape(len(states), N_ACTIONS))
        weights.append(1.0 - p if shift == 0 else p / (N_CUBES - 1))
    goal = is_goal(states, task).astype(np.float64)
    live = 1.0 - is_terminal(states, task)
    w = np.zeros(len(states))
    actions = np.zeros((horizon, len(states)), dtype=np.int64)
    for k in range(horizon):
        q = sum(weight * (goal[n] + live[n] * w[n])
                for weight, n in zip(weights, outcomes, strict=True))  # fmt: skip
        actions[k] = q.argmax(1)
        w = q.max(1) * live  # no action is taken from a terminal state
    return float(w[macrostate_index(start_states(task))].mean()), actions


def describe(state: Macrostate) -> str:
    """A short human-readable label, e.g. ``'↑ → ↓ | hand→1'``."""
    d0, d1, d2, h = (int(x) for x in state)
    return f"{DIRECTION_ARROWS[d0]} {DIRECTION_ARROWS[d1]} {DIRECTION_ARROWS[d2]} | hand→{h}"
