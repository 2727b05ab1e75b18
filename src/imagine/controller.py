"""C: the DQN controller (paper sections III-A and V-B, Controller).

A Q-network of 512-256-128 ReLU units and a linear output per action, trained on the squared TD
error (equation 2) toward ``y = r + gamma * (1 - d) * max_a' Q(s', a')`` (equation 1) with Adam.
The paper uses no target network; a target network (copied every ``target_update_period``
updates) and double DQN are options. Exploration is epsilon-greedy with
``epsilon = eps_min + (eps_max - eps_min) * exp(-lambda * t)``.
"""

from __future__ import annotations

import copy
import itertools
import math

import torch
from torch import nn
from torch.nn import functional as F


def epsilon(
    t: int | float, eps_min: float = 0.001, eps_max: float = 0.8, decay: float = 0.03
) -> float:
    """The paper's exploration rate at time ``t`` (what t counts is a config choice)."""
    return eps_min + (eps_max - eps_min) * math.exp(-decay * t)


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam with the fused kernel (one kernel for all parameters; same update rule)."""
    return torch.optim.Adam(params, lr=lr, fused=True)


def mlp(sizes: list[int], dropout: float = 0.0) -> nn.Sequential:
    """Linear layers with ReLU (and dropout) between them, none after the last."""
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(n_in, n_out))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


class Controller(nn.Module):
    """C: Q-values of every action for a latent state."""

    def __init__(
        self,
        latent_dim: int,
        n_actions: int = 6,
        hidden: tuple[int, ...] = (512, 256, 128),
        lr: float = 1e-3,
        gamma: float = 0.99,
        target_update_period: int = 0,
        double_dqn: bool = False,
    ) -> None:
        super().__init__()
        self.n_actions = n_actions
        self.gamma = gamma
        self.q = mlp([latent_dim, *hidden, n_actions])
        self.optimizer = adam(self.q.parameters(), lr)
        self.target_update_period = target_update_period
        self.double_dqn = double_dqn
        self.target = copy.deepcopy(self.q).requires_grad_(False) if target_update_period else None
        self.updates = 0

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.q(z)

    @torch.no_grad()
    def act(self, z: torch.Tensor, eps: float, generator: torch.Generator) -> torch.Tensor:
        """Epsilon-greedy actions for a batch of latents (N, latent_dim): int64 (N,)."""
        greedy = self.q(z).argmax(-1)
        n = len(z)
        explore = torch.rand(n, generator=generator, device=z.device) < eps
        random = torch.randint(self.n_actions, (n,), generator=generator, device=z.device)
        return torch.where(explore, random, greedy)

    @torch.no_grad()
    def td_target(
        self, reward: torch.Tensor, next_z: torch.Tensor, done: torch.Tensor
    ) -> torch.Tensor:
        """y = r + gamma * (1 - d) * Q'(s', argmax) (equation 1)."""
        bootstrap_net = self.target if self.target is not None else self.q
        if self.double_dqn:
            best = self.q(next_z).argmax(-1, keepdim=True)
            next_q = bootstrap_net(next_z).gather(-1, best).squeeze(-1)
        else:
            next_q = bootstrap_net(next_z).max(-1).values
        return reward + self.gamma * (1.0 - done) * next_q

    def update(
        self, z: torch.Tensor, action: torch.Tensor, reward: torch.Tensor,
        next_z: torch.Tensor, done: torch.Tensor,
    ) -> float:  # fmt: skip
        """One Adam step on the mean squared TD error (equation 2); returns the loss."""
        y = self.td_target(reward, next_z, done)
        q = self.q(z).gather(-1, action.unsqueeze(-1)).squeeze(-1)
        loss = F.mse_loss(q, y)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        if self.target is not None and self.updates % self.target_update_period == 0:
            self.target.load_state_dict(self.q.state_dict())
        return float(loss.detach())
