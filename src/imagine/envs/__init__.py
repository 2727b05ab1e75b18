"""Environments as Algorithm 1 sees them: an :class:`~imagine.envs.spec.EnvSpec` per kind.

- :mod:`imagine.envs.spec`: what the core needs of an environment, and :func:`make_spec`, which
  picks the spec of a config's ``env``;
- :mod:`imagine.envs.gym`: any registered Gymnasium environment with a Discrete action space
  (images, vectors, Discrete or Dict observations);
- GesturePuzzle, the paper's task, is :mod:`imagine.envs.gesture_puzzle` (its spec:
:mod:`imagine.envs.gesture_puzzle.spec`).
"""

from imagine.envs.spec import EnvSpec, make_spec

__all__ = ["EnvSpec", "make_spec"]
