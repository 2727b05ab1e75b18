"""Toy Gymnasium environments made in the test suite, so that nothing GesturePuzzle-only
creeps back into the core (issue 17): a walk to the right end of a line, seen as a vector, as a
Discrete state, as a small image, or as a grid of booleans (MinAtar's kind). Importing this
module registers them."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

LENGTH = 5
"""Positions 0..4; the goal is 4."""
STEP_REWARD, GOAL_REWARD = -0.1, 1.0


class Line(gym.Env):
    """Start at position 1 or 2; actions 0 left, 1 right, 2 stay; +1 and the end at the right
    end (``info["is_success"]``), -0.1 a step otherwise."""

    def __init__(self, observe: str = "vector") -> None:
        self.observe = observe
        self.action_space = gym.spaces.Discrete(3)
        if observe == "vector":
            self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        elif observe == "discrete":
            self.observation_space = gym.spaces.Discrete(LENGTH)
        elif observe == "image":
            self.observation_space = gym.spaces.Box(0, 255, (8, 8, 3), np.uint8)
        elif observe == "grid":  # one row of cells, two channels: the agent and the goal
            self.observation_space = gym.spaces.Box(0, 1, (1, LENGTH, 2), bool)
        else:
            self.observation_space = gym.spaces.Tuple((gym.spaces.Discrete(2),) * 2)
        self.position = 0

    def _obs(self):
        if self.observe == "vector":
            return np.array([self.position / (LENGTH - 1), 1.0], dtype=np.float32)
        if self.observe == "discrete":
            return self.position
        if self.observe == "grid":
            grid = np.zeros((1, LENGTH, 2), dtype=bool)
            grid[0, self.position, 0] = grid[0, LENGTH - 1, 1] = True
            return grid
        image = np.zeros((8, 8, 3), dtype=np.uint8)
        image[:, self.position] = 255
        return image

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position = int(self.np_random.integers(1, 3))
        return self._obs(), {}

    def step(self, action):
        self.position = int(np.clip(self.position + (-1, 1, 0)[int(action)], 0, LENGTH - 1))
        goal = self.position == LENGTH - 1
        reward = GOAL_REWARD if goal else STEP_REWARD
        return self._obs(), reward, goal, False, {"is_success": goal}


for _name, _observe in (("Line", "vector"), ("LineDiscrete", "discrete"),
                        ("LineImage", "image"), ("LineGrid", "grid"),
                        ("LineTuple", "tuple")):  # fmt: skip
    if f"imagine-test/{_name}-v0" not in gym.registry:
        gym.register(f"imagine-test/{_name}-v0", entry_point=Line, max_episode_steps=20,
                     kwargs={"observe": _observe})  # fmt: skip
