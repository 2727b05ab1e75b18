"""Many GesturePuzzle environments stepped as one batch.

:class:`GesturePuzzleVectorEnv` keeps every sub-environment's macrostate in one (N, 4) array and
synthesizes all N observations with one batched gather, so 1000 test episodes run at once.
Each sub-environment keeps its own random generator, seeded as Gymnasium's ``SyncVectorEnv``
seeds its copies (``seed + i``), and draws from it in the same order as
:class:`~imagine.envs.gesture_puzzle.environment.GesturePuzzleEnv`: the vector environment matches
N single environments step for step, autoresets included.

Autoreset follows Gymnasium's modes: ``NEXT_STEP`` (default, as ``SyncVectorEnv``: the step
after an episode ends resets that sub-environment and ignores its action, with reward 0) or
``SAME_STEP`` (the reset happens in the step that ends the episode; the last observation and
macrostate go to ``info["final_obs"]`` and ``info["final_macrostate"]``, marked by
``info["_final_obs"]``) or ``DISABLED`` (no resets but those asked for with
``reset(options={"reset_mask": ...})``; until then a sub-environment whose episode ended is
not stepped: its action is ignored, its reward is 0, it is not terminated or truncated again,
its observation stays and its generator draws nothing, so N test episodes cost only the
running ones). ``info["macrostate"]`` is an int64 (N, 4) array and ``info["actions"]`` the
actions taken so far in each episode.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from imagine.envs.gesture_puzzle import rules
from imagine.envs.gesture_puzzle.environment import FragmentSource, check_macrostate, make_composer
from imagine.envs.gesture_puzzle.scene import OBS_SIZE
from imagine.errors import ConfigError


class GesturePuzzleVectorEnv(VectorEnv):
    """``num_envs`` GesturePuzzle environments in one batch; other arguments as
    :class:`~imagine.envs.gesture_puzzle.environment.GesturePuzzleEnv`.

    ``reset(options={"macrostates": array (N, 4)})`` starts each sub-environment from a given
    legal non-goal state; ``options={"reset_mask": bool (N,)}`` resets only some of them.
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "render_fps": 2,
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int,
        task: str = "original",
        fragments: FragmentSource = None,
        fragment_seed: int = 0,
        n_cube_fragments: int = 16,
        n_hand_fragments: int = 50,
        render_mode: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        hand_switch_prob: float = 0.0,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ConfigError(f"num_envs must be a positive integer, got {num_envs!r}")
        num_envs = int(num_envs)
        try:
            self.task = rules.check_task(task)
            self.hand_switch_prob = rules.check_hand_switch_prob(hand_switch_prob)
            mode = AutoresetMode(autoreset_mode)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED):
            raise ConfigError(
                f"autoreset_mode must be NEXT_STEP, SAME_STEP or DISABLED, got {mode.value}"
            )
        if render_mode is not None and render_mode != "rgb_array":
            raise ConfigError(f"unknown render_mode {render_mode!r}; choose 'rgb_array' or None")
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        self.autoreset_mode = mode
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.composer = make_composer(fragments, fragment_seed, n_cube_fragments, n_hand_fragments)
        self.single_observation_space = gym.spaces.Box(0, 255, (OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.single_action_space = gym.spaces.Discrete(rules.N_ACTIONS)
        self.action_space = batch_space(self.single_action_space, num_envs)
        # made on first use: an unseeded generator draws OS entropy (0.2 ms each), and a
        # reset with a seed replaces it anyway
        self._rngs: list[np.random.Generator | None] = [None] * num_envs
        self._states = np.zeros((num_envs, 4), dtype=np.int64)
        self._fragments = np.zeros((num_envs, 4), dtype=np.int64)
        self._actions = np.zeros(num_envs, dtype=np.int64)
        # NEXT_STEP: reset at the next step; DISABLED: ended, not stepped until reset
        self._autoreset = np.zeros(num_envs, dtype=bool)
        self._last_obs: np.ndarray | None = None

    @functools.cached_property
    def observation_space(self) -> gym.spaces.Box:
        """The batched observation space, built on first use: its bounds are two arrays of
        every pixel of every sub-environment (12 M values each for 1000), which Gymnasium checks
        element by element, 0.3 s that an evaluation never needs."""
        return batch_space(self.single_observation_space, self.num_envs)

    # --- random draws, per sub-environment and in the single environment's order ----------------

    def _rng(self, i: int) -> np.random.Generator:
        """Sub-environment i's generator (an unseeded one if it was never seeded)."""
        if self._rngs[i] is None:
            self._rngs[i], _ = seeding.np_random()
        return self._rngs[i]

    def _draw_starts(self, envs: np.ndarray) -> None:
        starts = rules.start_states(self.task)
        for i in envs:
            self._states[i] = starts[self._rng(i).integers(len(starts))]

    def _observe(self, envs: np.ndarray) -> None:
        pool = self.composer.pool
        for i in envs:
            self._fragments[i] = pool.sample_indices(self._rng(i), self._states[i])

    def _observation(self) -> np.ndarray:
        return self.composer.observe(self._states, self._fragments)

    def _info(self) -> dict[str, Any]:
        return {"macrostate": self._states.copy(), "actions": self._actions.copy()}

    # --- the Gymnasium API ---------------------------------------------------------------------

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, dtype=bool)))
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(
                f"options['reset_mask'] must be a bool array of shape ({self.num_envs},)"
            )
        seeds = self._seed_list(seed)
        envs = np.flatnonzero(mask)
        for i in envs:
            if seeds[i] is not None:
                self._rngs[i], _ = seeding.np_random(seeds[i])
        starts = options.pop("macrostates", None)
        if starts is None:
            self._draw_starts(envs)
        else:
            starts = np.asarray(starts)
            if starts.shape != (self.num_envs, 4):
                raise ValueError(f"options['macrostates'] must have shape ({self.num_envs}, 4)")
            for i in envs:
                self._states[i] = check_macrostate(starts[i], self.task)
        self._actions[envs] = 0
        self._autoreset[envs] = False
        self._observe(envs)
        obs = self._observation()
        self._hold(obs)
        return obs, self._info()

    def _hold(self, obs: np.ndarray) -> None:
        """Keep the observations a held sub-environment shows again (DISABLED mode only; a
        copy, so that a caller may change what it was given)."""
        if self.autoreset_mode == AutoresetMode.DISABLED:
            self._last_obs = obs.copy()

    def _seed_list(self, seed: int | list[int | None] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, int):
            return [seed + i for i in range(self.num_envs)]
        if len(seed) != self.num_envs:
            raise ValueError(f"got {len(seed)} seeds for {self.num_envs} environments")
        return list(seed)

    def _check_actions(self, actions: Any) -> np.ndarray:
        a = np.asarray(actions)
        if a.shape != (self.num_envs,) or not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"actions must be {self.num_envs} integers in 0..5, got {actions!r}")
        if ((a < 0) | (a >= rules.N_ACTIONS)).any():
            bad = a[(a < 0) | (a >= rules.N_ACTIONS)][0]
            raise ValueError(f"invalid action {int(bad)}: expected an integer in 0..5")
        return a.astype(np.int64)

    def step(
        self, actions: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        a = self._check_actions(actions)
        resetting = self._autoreset.copy()
        stepping = ~resetting
        self._states[stepping] = rules.apply_actions(self._states[stepping], a[stepping])
        if self.hand_switch_prob > 0:  # each env draws from its own stream, as it does alone
            for i in np.flatnonzero(stepping):
                self._states[i] = rules.move_hand(self._states[i], self.hand_switch_prob,
                                                  self._rng(i))  # fmt: skip
        self._actions[stepping] += 1
        terminated = rules.is_terminal(self._states, self.task) & stepping
        truncated = ~terminated & stepping & (self._actions >= rules.MAX_EPISODE_ACTIONS)
        reward = np.where(stepping, rules.rewards(self._states, self.task), 0.0)
        info: dict[str, Any] = {}
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            done = terminated | truncated
            self._observe(np.arange(self.num_envs))
            final_obs = self._observation()
            info = {"final_obs": final_obs, "final_macrostate": self._states.copy(),
                    "_final_obs": done}  # fmt: skip
            ended = np.flatnonzero(done)
            self._draw_starts(ended)
            self._actions[done] = 0
            self._observe(ended)
            obs = final_obs.copy()  # only the ended episodes' observations change
            obs[ended] = self.composer.observe(self._states[ended], self._fragments[ended])
        elif self.autoreset_mode == AutoresetMode.DISABLED:
            moved = np.flatnonzero(stepping)
            self._observe(moved)
            if len(moved) == self.num_envs:
                obs = self._observation()
            else:  # the ended ones keep their last observation (_hold stores a copy)
                obs = self._last_obs
                obs[moved] = self.composer.observe(self._states[moved], self._fragments[moved])
            self._autoreset |= terminated | truncated  # ended: not stepped until reset
        else:
            self._draw_starts(np.flatnonzero(resetting))
            self._actions[resetting] = 0
            self._observe(np.arange(self.num_envs))
            self._autoreset = terminated | truncated
            obs = self._observation()
        self._hold(obs)
        return (
            obs,
            reward.astype(np.float64),
            terminated,
            truncated,
            {
                **self._info(),
                **info,
            },
        )

    def render(self) -> tuple[np.ndarray, ...] | None:
        """The full scene of every sub-environment, RGB uint8 (H, W, 3) each."""
        if self.render_mode != "rgb_array":
            return None
        return tuple(
            np.repeat(self.composer.scene(s, f)[..., None], 3, axis=-1)
            for s, f in zip(self._states, self._fragments, strict=True)
        )
