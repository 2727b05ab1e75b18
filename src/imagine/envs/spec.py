"""The seam between Algorithm 1 and an environment.

:class:`~imagine.learning.population.Population` trains P agents in lockstep on one Gymnasium vector
environment (autoreset disabled: each agent's episodes start when the population says so). What
it needs of the environment beyond Gymnasium's API is an :class:`EnvSpec`: how to make that
vector environment, how many actions there are, what the encoder reads from a step's
``(obs, info)``, whether an episode reached its goal, and how each agent's episodes are seeded
so that a run stopped and resumed continues with the same episodes.
"""

from __future__ import annotations

import functools
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.vector import VectorEnv

from imagine import ENV_ID


class EnvSpec(Protocol):
    """What the core needs of an environment."""

    env_id: str
    """The Gymnasium id it was made from."""
    n_actions: int
    """C's outputs and M's action inputs: the size of the Discrete action space."""
    observation_space: gym.Space
    """One environment's observation space (what the encoder is built for)."""

    def make_vector_env(self, n: int) -> VectorEnv:
        """``n`` copies in one vector environment, autoreset disabled."""
        ...

    def reset_seed(self, seed: int, episode: int) -> int | None:
        """The seed of an agent's reset before its episode ``episode`` (0 = first): None keeps
        the environment's own random stream (then :meth:`env_state` must save it)."""
        ...

    def encoder_input(self, obs: Any, info: dict[str, Any]) -> tuple[np.ndarray, Any]:
        """What the encoder reads from a vector step: ``(x, extra)``, each indexable by agent
        (``extra`` None when the encoder needs only ``x``)."""
        ...

    def success(self, reward: np.ndarray, info: dict[str, Any]) -> np.ndarray | None:
        """bool (N,): which steps reached the goal; None where the env does not say."""
        ...

    def env_state(self, envs: VectorEnv, i: int) -> Any:
        """A JSON-able state of agent i's environment stream for its checkpoint (or None)."""
        ...

    def set_env_state(self, envs: VectorEnv, i: int, state: Any) -> None:
        """Restore what :meth:`env_state` saved."""
        ...


def make_spec(config) -> EnvSpec:
    """The spec of an :class:`~imagine.config.AgentConfig`'s ``env`` (GesturePuzzle with its
    ``task`` and ``hand_switch_prob``, or any registered Gymnasium environment with its
    ``wrappers``)."""
    if config.env == ENV_ID:
        from imagine.envs.gesture_puzzle.spec import GesturePuzzleSpec

        return GesturePuzzleSpec(config.task, config.hand_switch_prob)
    return gym_spec(config.env, tuple(config.wrappers))


@functools.cache
def gym_spec(env_id: str, wrappers: tuple[str, ...]) -> EnvSpec:
    """One GymSpec per (env, wrappers) and process: building it makes a probe env, and a
    command asks for the spec several times (encoder choice, V, the agent)."""
    from imagine.envs.gym import GymSpec

    return GymSpec(env_id, wrappers)


def episode_seed(seed: int, k: int) -> int:
    """The reset seed of test episode k."""
    return int(np.random.SeedSequence([seed, k]).generate_state(1)[0])


def reset_ended(envs: VectorEnv, ended: np.ndarray, episodes: np.ndarray, seed: int) -> tuple:
    """Reset the copies of a vector env whose episodes ``ended`` (bool, per copy), copy i into
    episode ``episodes[i]`` of a collection seeded by ``seed`` (:func:`episode_seed`); the
    others go on. Test episodes and V's random frames both run copies this way, so episode k
    is the same whichever copy runs it."""
    seeds = [
        episode_seed(seed, int(k)) if e else None for k, e in zip(episodes, ended, strict=True)
    ]
    return envs.reset(seed=seeds, options={"reset_mask": ended})
