"""A perfect M for CartPole-v1 and Acrobot-v1: the environment's own dynamics.

Their observation is their state (Acrobot's with each angle as its cosine and sine), so the
environment itself, set to an imagined state and stepped, gives the true next state, and its
rules the reward and the end. With ``imagination_model: true`` the agent imagines with this in
place of its learned M: a diagnostic that separates "imagined data cannot help here" from "our
M is wrong" (issue 57), never a result. Truncation by a time limit is not part of the dynamics.
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import torch

from imagine.models.world_model import Prediction


class ClassicTrueModel:
    """An environment's dynamics as an M in population form (the calls
    :func:`imagine.learning.imagination.imagine_rollouts` makes): ``predict``, ``is_terminal``
    and ``predict_reward`` on latents (P, B, D), which are the observations themselves."""

    env_id = ""

    def __init__(self) -> None:
        self.env = gym.make(self.env_id).unwrapped
        self.env.reset(seed=0)

    def set_state(self, obs: np.ndarray) -> None:
        """Put the environment in the state an observation shows."""
        raise NotImplementedError

    def terminal(self, obs: np.ndarray) -> np.ndarray:
        """Whether each observation (N, D) is a terminal state."""
        raise NotImplementedError

    def reward(self, obs: np.ndarray) -> np.ndarray:
        """The reward for entering each state (N, D)."""
        raise NotImplementedError

    @torch.no_grad()
    def predict(
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generators: Sequence[torch.Generator | None] = (),
        draw: str = "mode",
    ) -> Prediction:
        """The true next state of each row (deterministic dynamics: every draw is the same);
        no disagreement."""
        states = z.reshape(-1, z.shape[-1]).cpu().numpy().astype(np.float64)
        actions = action.reshape(-1).cpu().numpy()
        out = np.empty_like(states)
        for i, (state, a) in enumerate(zip(states, actions, strict=True)):
            self.set_state(state)
            out[i] = self.env.step(int(a))[0]
        next_z = torch.as_tensor(out, dtype=z.dtype, device=z.device).view(z.shape)
        return Prediction(next_z, torch.zeros(z.shape[:-1], device=z.device))

    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        done = self.terminal(z.reshape(-1, z.shape[-1]).cpu().numpy())
        return torch.as_tensor(done, device=z.device).view(z.shape[:-1])

    def predict_reward(self, z: torch.Tensor) -> torch.Tensor:
        r = self.reward(z.reshape(-1, z.shape[-1]).cpu().numpy())
        return torch.as_tensor(r, dtype=torch.float32, device=z.device).view(z.shape[:-1])


class CartPoleTrueModel(ClassicTrueModel):
    """CartPole-v1: the state is (x, x_dot, theta, theta_dot); the episode ends when the cart
    or the pole passes the environment's thresholds; every step, the last included, pays 1."""

    env_id = "CartPole-v1"

    def set_state(self, obs: np.ndarray) -> None:
        self.env.state = obs.copy()
        self.env.steps_beyond_terminated = None  # stepping from any state is a fresh step

    def terminal(self, obs: np.ndarray) -> np.ndarray:
        return (np.abs(obs[:, 0]) > self.env.x_threshold) | (
            np.abs(obs[:, 2]) > self.env.theta_threshold_radians
        )

    def reward(self, obs: np.ndarray) -> np.ndarray:
        return np.ones(len(obs))


class AcrobotTrueModel(ClassicTrueModel):
    """Acrobot-v1: the observation is (cos t1, sin t1, cos t2, sin t2, t1_dot, t2_dot); the
    episode ends when the tip is a link's length above the base,
    -cos t1 - cos(t1 + t2) > 1; a step pays -1, the last 0."""

    env_id = "Acrobot-v1"

    def set_state(self, obs: np.ndarray) -> None:
        t1, t2 = np.arctan2(obs[1], obs[0]), np.arctan2(obs[3], obs[2])
        self.env.state = np.array([t1, t2, obs[4], obs[5]])

    def terminal(self, obs: np.ndarray) -> np.ndarray:
        cos_sum = obs[:, 0] * obs[:, 2] - obs[:, 1] * obs[:, 3]  # cos(t1 + t2)
        return -obs[:, 0] - cos_sum > 1.0

    def reward(self, obs: np.ndarray) -> np.ndarray:
        return np.where(self.terminal(obs), 0.0, -1.0)


TRUE_MODELS = {m.env_id: m for m in (CartPoleTrueModel, AcrobotTrueModel)}
"""Each environment's true model, by Gymnasium id."""


def random_transitions(env_id: str, n: int = 2000, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` real transitions of a uniform random policy (episodes from ``reset(seed)`` on,
    their terminal steps included): state, action, next state, reward, terminated. Held out:
    no agent trains on them."""
    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {k: [] for k in ("state", "action", "next", "reward", "done")}
    obs, _ = env.reset(seed=seed)
    while len(rows["state"]) < n:
        a = int(rng.integers(env.action_space.n))
        nxt, r, terminated, truncated, _ = env.step(a)
        for key, value in zip(rows, (obs, a, nxt, r, terminated), strict=True):
            rows[key].append(value)
        obs = env.reset()[0] if terminated or truncated else nxt
    env.close()
    return {k: np.asarray(v) for k, v in rows.items()}
