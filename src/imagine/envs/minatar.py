"""MinAtar (Young & Tian 2019, ``pip install 'imagine[minatar]'``) as Gymnasium environments.

Importing this module registers MinAtar's own environments (``MinAtar/<Game>-v0`` with the
game's full action set, ``-v1`` with its minimal one: Breakout-v1 has 3 actions, no-op, left and
right), so ``--env imagine.envs.minatar:MinAtar/Breakout-v1`` works wherever an environment is
named. Their observation is a 10 x 10 x n grid of booleans (one channel per kind of object),
which the vector encoder flattens into C's and M's 10 * 10 * n inputs
(:class:`~imagine.models.encoders.VectorEncoder`). MinAtar's own defaults hold: sticky actions
(the previous action repeats with probability 0.1) and no time limit.
"""

from __future__ import annotations

import gymnasium as gym

try:
    from minatar import gym as minatar_gym
except ImportError as error:  # extras_of turns this into a one-line ConfigError
    raise ImportError(
        f"MinAtar is not installed ({error}): pip install 'imagine[minatar]'"
    ) from None

if "MinAtar/Breakout-v1" not in gym.registry:
    minatar_gym.register_envs()
