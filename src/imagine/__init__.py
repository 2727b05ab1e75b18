"""imagine: sample-efficient deep RL with imaginary rollouts (Thabet et al. 2019).

Importing the package registers the paper's environment with Gymnasium, so that::

    import gymnasium, imagine
    env = gymnasium.make("imagine/GesturePuzzle-v0", task="hard")

works without importing :mod:`imagine.envs.gesture_puzzle` first (registration only names the entry
points; the environment's modules load on the first ``make``).
"""

import gymnasium as _gym

ENV_ID = "imagine/GesturePuzzle-v0"
"""GesturePuzzle's Gymnasium id; the task is a keyword (``task="original"`` or ``"hard"``)."""

if ENV_ID not in _gym.registry:
    _gym.register(
        id=ENV_ID,
        entry_point="imagine.envs.gesture_puzzle.environment:GesturePuzzleEnv",
        vector_entry_point="imagine.envs.gesture_puzzle.vector:GesturePuzzleVectorEnv",
        max_episode_steps=None,
    )

EXTRAS: dict[str, str] = {
    ENV_ID: "imagine.envs.gesture_puzzle.extras:EXTRAS",
    "CartPole-v1": "imagine.envs.classic_control.extras:EXTRAS",
    "Acrobot-v1": "imagine.envs.classic_control.extras:EXTRAS",
}
"""Each environment's extras for Algorithm 1 (its encoder, a probe of M, its true dynamics), by
entry point: :mod:`imagine.learning.extras`."""
