"""GesturePuzzle: the human-robot interaction task of the paper (docs/design.md section 1).

Registered with Gymnasium as ``imagine/GesturePuzzle-v0``; the task is a keyword::

    env = gymnasium.make("imagine/GesturePuzzle-v0", task="hard")
    envs = gymnasium.make_vec("imagine/GesturePuzzle-v0", num_envs=1000, task="hard",
                              vectorization_mode="vector_entry_point")
"""

from imagine import ENV_ID  # registered with Gymnasium by importing the package
from imagine.envs.gesture_puzzle.environment import GesturePuzzleEnv, make_composer
from imagine.envs.gesture_puzzle.fragments import (
    FragmentPool,
    load_fragment_folder,
    procedural_pool,
    save_fragment_folder,
)
from imagine.envs.gesture_puzzle.rules import optimal_plan_length, transition
from imagine.envs.gesture_puzzle.scene import SceneComposer
from imagine.envs.gesture_puzzle.vector import GesturePuzzleVectorEnv

__all__ = [
    "ENV_ID",
    "FragmentPool",
    "GesturePuzzleEnv",
    "GesturePuzzleVectorEnv",
    "SceneComposer",
    "load_fragment_folder",
    "make_composer",
    "optimal_plan_length",
    "procedural_pool",
    "save_fragment_folder",
    "transition",
]
