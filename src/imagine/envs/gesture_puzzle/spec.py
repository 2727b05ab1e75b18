"""GesturePuzzle as Algorithm 1 sees it (:class:`~imagine.envs.spec.EnvSpec`).

Its batched vector environment
(:class:`~imagine.envs.gesture_puzzle.vector.GesturePuzzleVectorEnv`), 6 actions, success when the
goal's reward comes, and the true macrostate in ``info`` beside the image (the oracle encoder reads
it; V reads the image). Each agent's environment keeps its own random stream from its first seeded
reset; the checkpoint saves it.
"""

from __future__ import annotations

import json
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from imagine import ENV_ID
from imagine.envs.gesture_puzzle.rules import N_ACTIONS, REWARD_GOAL
from imagine.envs.gesture_puzzle.vector import GesturePuzzleVectorEnv


class GesturePuzzleSpec:
    """The paper's task (``task``: original or hard; ``hand_switch_prob``: a stochastic
    human)."""

    env_id = ENV_ID
    n_actions = N_ACTIONS

    def __init__(self, task: str = "original", hand_switch_prob: float = 0.0) -> None:
        self.task = task
        self.hand_switch_prob = hand_switch_prob

    @property
    def observation_space(self) -> gym.Space:
        return GesturePuzzleVectorEnv(1, task=self.task).single_observation_space

    def make_vector_env(self, n: int) -> GesturePuzzleVectorEnv:
        return GesturePuzzleVectorEnv(n, task=self.task, autoreset_mode=AutoresetMode.DISABLED,
                                      hand_switch_prob=self.hand_switch_prob)  # fmt: skip

    def reset_seed(self, seed: int, episode: int) -> int | None:
        return None  # one stream per agent from its first reset, saved in checkpoints

    def encoder_input(self, obs: np.ndarray, info: dict[str, Any]) -> tuple[np.ndarray, Any]:
        return obs, info["macrostate"]

    def success(self, reward: np.ndarray, info: dict[str, Any]) -> np.ndarray:
        return np.asarray(reward) == REWARD_GOAL

    def env_state(self, envs: GesturePuzzleVectorEnv, i: int) -> Any:
        return json.loads(json.dumps(envs._rng(i).bit_generator.state))

    def set_env_state(self, envs: GesturePuzzleVectorEnv, i: int, state: Any) -> None:
        envs._rng(i).bit_generator.state = state
