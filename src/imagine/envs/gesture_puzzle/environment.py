"""GesturePuzzle as a Gymnasium environment (docs/design.md section 1; paper section V-A).

The agent sees only images: a uint8 (64, 64, 3) observation whose channels are the three strips
of the scene, one cube each. The macrostate ``(d0, d1, d2, h)`` goes in ``info["macrostate"]``
for evaluation, never in the observation.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from imagine.envs.gesture_puzzle import rules
from imagine.envs.gesture_puzzle.fragments import (
    FragmentPool,
    load_fragment_folder,
    procedural_pool,
)
from imagine.envs.gesture_puzzle.scene import OBS_SIZE, SceneComposer
from imagine.errors import ConfigError

FragmentSource = FragmentPool | str | Path | None


@lru_cache(maxsize=8)
def _composer_for_pool(pool: FragmentPool) -> SceneComposer:
    return SceneComposer(pool)


def make_composer(
    fragments: FragmentSource = None,
    fragment_seed: int = 0,
    n_cube_fragments: int = 16,
    n_hand_fragments: int = 50,
) -> SceneComposer:
    """The image synthesizer for a fragment source: ``None`` for the procedural renderer (seeded
    by ``fragment_seed``, with the given pool sizes), a folder of photographs, or a pool."""
    if fragments is None:
        pool = procedural_pool(fragment_seed, n_cube_fragments, n_hand_fragments)
    elif isinstance(fragments, FragmentPool):
        pool = fragments
    elif isinstance(fragments, str | Path):
        pool = load_fragment_folder(fragments)
    else:
        raise ConfigError(f"fragments must be None, a folder or a FragmentPool, got {fragments!r}")
    return _composer_for_pool(pool)


def check_macrostate(state: Any, task: str) -> np.ndarray:
    """A start macrostate given by the user, as int64 (4,); must be a legal non-goal state."""
    s = np.asarray(state)
    if s.shape != (4,) or not np.issubdtype(s.dtype, np.integer):
        raise ValueError(f"macrostate must be 4 integers (d0, d1, d2, h), got {state!r}")
    if not (
        (s[:3] >= 0).all() and (s[:3] < rules.N_DIRECTIONS).all() and 0 <= s[3] < rules.N_CUBES
    ):
        raise ValueError(
            f"macrostate {tuple(int(x) for x in s)} is out of range: d_i in 0..3, h in 0..2"
        )
    if rules.is_terminal(s, task):
        raise ValueError(f"macrostate {tuple(int(x) for x in s)} is terminal in task {task!r}")
    return s.astype(np.int64)


class GesturePuzzleEnv(gym.Env):
    """Rotate three cubes until the arrow on the cube the human points at faces the human.

    Args:
        task: ``"original"`` (goal: legal and ``d_h == DOWN``) or ``"hard"`` (also no arrow UP).
        fragments: ``None`` (procedural renderer), a folder of fragment photographs, or a pool.
        fragment_seed: seed of the procedural renderer (the pool of fragments, not the episodes).
        n_cube_fragments: procedural fragments per (cube, direction); the paper's 16.
        n_hand_fragments: procedural fragments per pointed cube; the paper's 50.
        render_mode: ``"rgb_array"`` to let :meth:`render` return the full scene.
        hand_switch_prob: a stochastic human (issue 16): the probability that the hand moves
            to another cube after each action (0, the default: the paper's task).

    ``reset(options={"macrostate": (d0, d1, d2, h)})`` starts from a given legal non-goal state.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        task: str = "original",
        fragments: FragmentSource = None,
        fragment_seed: int = 0,
        n_cube_fragments: int = 16,
        n_hand_fragments: int = 50,
        render_mode: str | None = None,
        hand_switch_prob: float = 0.0,
    ) -> None:
        try:
            self.task = rules.check_task(task)
            self.hand_switch_prob = rules.check_hand_switch_prob(hand_switch_prob)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(f"unknown render_mode {render_mode!r}; choose 'rgb_array' or None")
        self.render_mode = render_mode
        self.composer = make_composer(fragments, fragment_seed, n_cube_fragments, n_hand_fragments)
        self.observation_space = gym.spaces.Box(0, 255, (OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.action_space = gym.spaces.Discrete(rules.N_ACTIONS)
        self._state = np.zeros(4, dtype=np.int64)
        self._fragments = np.zeros(4, dtype=np.int64)
        self._actions = 0

    @property
    def macrostate(self) -> rules.Macrostate:
        return tuple(int(x) for x in self._state)  # type: ignore[return-value]

    def _observe(self) -> np.ndarray:
        self._fragments = self.composer.pool.sample_indices(self.np_random, self._state)
        return self.composer.observe(self._state, self._fragments)

    def _info(self) -> dict[str, Any]:
        return {"macrostate": self.macrostate, "actions": self._actions}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        start = (options or {}).get("macrostate")
        if start is None:
            starts = rules.start_states(self.task)
            self._state = starts[self.np_random.integers(len(starts))].copy()
        else:
            self._state = check_macrostate(start, self.task)
        self._actions = 0
        return self._observe(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = rules.check_action(action)
        self._state = rules.apply_actions(self._state, np.int64(a))
        self._state = rules.move_hand(self._state, self.hand_switch_prob, self.np_random)
        self._actions += 1
        terminated = bool(rules.is_terminal(self._state, self.task))
        truncated = not terminated and self._actions >= rules.MAX_EPISODE_ACTIONS
        reward = float(rules.rewards(self._state, self.task))
        return self._observe(), reward, terminated, truncated, self._info()

    def render(self) -> np.ndarray | None:
        """The full scene the observation was cut from, as an RGB uint8 (H, W, 3) array."""
        if self.render_mode != "rgb_array":
            return None
        gray = self.composer.scene(self._state, self._fragments)
        return np.repeat(gray[..., None], 3, axis=-1)
