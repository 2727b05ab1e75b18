"""Any registered Gymnasium environment with a Discrete action space, as Algorithm 1 sees it.

``env_id`` is what ``gymnasium.make`` takes (``"CartPole-v1"``, or ``"module:Id"`` to import
the module that registers it); ``wrappers`` are ``"module:Class"`` names applied in order to
each copy. What the encoder reads depends on the observation space (:func:`observation_kind`):
images (an H x W x C uint8 Box) go to V, any other Box (a vector, a grid) passes as it is
(flattened), a Discrete observation as its one-hot vector, a Dict with an ``"image"`` entry as
that image; anything else is refused, naming the space. Success is ``info["is_success"]``
where the environment sets it. Each agent's episode e starts from ``reset(seed=...)`` with a
seed drawn from (agent seed, e), so a run stopped between episodes resumes with the same
episodes without saving the environment's state.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from imagine.errors import ConfigError

OBSERVATION_KINDS = ("image", "vector", "discrete")


def observation_kind(space: gym.Space) -> str:
    """What an observation space holds for the encoder: ``image`` (an H x W x C uint8 Box),
    ``vector`` (any other Box: a 1-D vector, or a grid such as MinAtar's 10 x 10 x n booleans,
    which the vector encoder flattens) or ``discrete``; a one-line error for any other space."""
    if isinstance(space, gym.spaces.Dict) and "image" in space.spaces:
        space = space.spaces["image"]
        if not _is_image(space):
            raise ConfigError(
                f"the observation's 'image' entry is not an H x W x C uint8 image: {space}"
            )
    if _is_image(space):
        return "image"
    if isinstance(space, gym.spaces.Box) and len(space.shape) >= 1:
        return "vector"  # a grid of numbers (MinAtar's booleans) too: flattened
    if isinstance(space, gym.spaces.Discrete):
        return "discrete"
    raise ConfigError(
        f"observation space {space} is not supported: an image (H x W x C uint8 Box), a vector "
        "or grid (any other Box), Discrete, or a Dict with an 'image' entry"
    )


def _is_image(space: gym.Space) -> bool:
    return (
        isinstance(space, gym.spaces.Box)
        and len(space.shape) == 3
        and space.shape[-1] in (1, 3, 4)
        and space.dtype == np.uint8
    )


def load_wrapper(name: str) -> Callable[[gym.Env], gym.Env]:
    """The wrapper class ``"module:Class"`` names; a one-line error if it cannot be imported."""
    module_name, sep, attribute = name.partition(":")
    if not sep or not module_name or not attribute:
        raise ConfigError(f"a wrapper is named module:Class, got {name!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"wrapper {name}: cannot import {module_name} ({exc})") from None
    wrapper = getattr(module, attribute, None)
    if not callable(wrapper):
        raise ConfigError(f"wrapper {name}: {module_name} has no class {attribute}")
    return wrapper


def make_env(env_id: str, wrappers: Sequence[str] = ()) -> gym.Env:
    """One copy of the environment, wrapped; a one-line error for an unknown id."""
    try:
        env = gym.make(env_id)
    except (gym.error.Error, ImportError, ModuleNotFoundError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"env {env_id}: {message}") from None
    for name in wrappers:
        env = load_wrapper(name)(env)
    return env


class GymSpec:
    """A registered Gymnasium environment (``env_id``, ``wrappers``) as an
    :class:`~imagine.envs.spec.EnvSpec`."""

    def __init__(self, env_id: str, wrappers: Sequence[str] = ()) -> None:
        self.env_id = env_id
        self.wrappers = tuple(wrappers)
        probe = make_env(env_id, self.wrappers)
        action_space, self.observation_space = probe.action_space, probe.observation_space
        probe.close()
        if not isinstance(action_space, gym.spaces.Discrete):
            raise ConfigError(
                f"env {env_id}: Algorithm 1 needs a Discrete action space, got {action_space}"
            )
        if int(action_space.start) != 0:
            raise ConfigError(f"env {env_id}: Discrete actions must start at 0, got {action_space}")
        self.n_actions = int(action_space.n)
        self.kind = observation_kind(self.observation_space)
        self._dict = isinstance(self.observation_space, gym.spaces.Dict)

    def make_vector_env(self, n: int) -> SyncVectorEnv:
        return SyncVectorEnv([self._make] * n, autoreset_mode=AutoresetMode.DISABLED)

    def _make(self) -> gym.Env:
        return make_env(self.env_id, self.wrappers)

    def reset_seed(self, seed: int, episode: int) -> int | None:
        return int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])

    def encoder_input(self, obs: Any, info: dict[str, Any]) -> tuple[np.ndarray, Any]:
        return (obs["image"] if self._dict else obs), None

    def success(self, reward: np.ndarray, info: dict[str, Any]) -> np.ndarray | None:
        if "is_success" not in info:
            return None
        reported = np.asarray(info.get("_is_success", np.ones(len(reward), dtype=bool)))
        return np.asarray(info["is_success"], dtype=bool) & reported

    def env_state(self, envs: SyncVectorEnv, i: int) -> Any:
        return None  # every episode is seeded: nothing to save

    def set_env_state(self, envs: SyncVectorEnv, i: int, state: Any) -> None:
        pass
