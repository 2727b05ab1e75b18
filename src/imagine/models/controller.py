"""C: the DQN controller (paper sections III-A and V-B, Controller).

A Q-network of 512-256-128 ReLU units and a linear output per action, trained on the squared TD
error (equation 2) toward ``y = r + gamma * (1 - d) * max_a' Q(s', a')`` (equation 1) with Adam.
The paper uses no target network; a target network (copied every ``target_update_period``
updates) and double DQN are options. Exploration is epsilon-greedy with
``epsilon = eps_min + (eps_max - eps_min) * exp(-lambda * t)``.

:class:`Controller` is one agent's C (what a checkpoint holds and what evaluation and planning
use); :class:`PopulationController` is the C of P agents trained together (weights with a
leading agent axis, :mod:`imagine.models.stacked`), with each agent's own exploration draws, Adam
state and target network.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

from imagine.models.stacked import PopulationAdam, StackedMLP


def epsilon(
    t: int | float, eps_min: float = 0.001, eps_max: float = 0.8, decay: float = 0.03
) -> float:
    """The paper's exploration rate at time ``t`` (what t counts is a config choice)."""
    return eps_min + (eps_max - eps_min) * math.exp(-decay * t)


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
        self, latent_dim: int, n_actions: int = 6, hidden: tuple[int, ...] = (512, 256, 128)
    ) -> None:
        super().__init__()
        self.n_actions = n_actions
        self.q = mlp([latent_dim, *hidden, n_actions])

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.q(z)


class PopulationController(nn.Module):
    """The C of P agents, each starting from its own :class:`Controller`."""

    def __init__(
        self,
        controllers: Sequence[Controller],
        lr: float = 1e-3,
        gamma: float = 0.99,
        target_update_period: int = 0,
        double_dqn: bool = False,
    ) -> None:
        super().__init__()
        self.n_actions = controllers[0].n_actions
        self.gamma = gamma
        self.q = StackedMLP([c.q for c in controllers])
        self.target_update_period = target_update_period
        self.double_dqn = double_dqn
        self.target = None
        if target_update_period:
            self.target = StackedMLP([c.q for c in controllers]).requires_grad_(False)
        self.optimizer = PopulationAdam(self.q.parameters(), len(controllers), lr)
        self.updates = torch.zeros(len(controllers), dtype=torch.int64)
        """C updates each agent has taken (real and imaginary)."""

    @torch.no_grad()
    def act(
        self,
        z: torch.Tensor,
        eps: Sequence[float],
        generators: Sequence[torch.Generator | None],
    ) -> torch.Tensor:
        """Epsilon-greedy actions for latents (P, N, latent_dim): int64 (P, N). Agent i draws
        from ``generators[i]`` (none if it is None: it gets its greedy actions)."""
        actions = self.q(z).argmax(-1)
        n = z.shape[1]
        for i, generator in enumerate(generators):
            if generator is None:
                continue
            explore = torch.rand(n, generator=generator, device=z.device) < eps[i]
            random = torch.randint(self.n_actions, (n,), generator=generator, device=z.device)
            actions[i] = torch.where(explore, random, actions[i])
        return actions

    @torch.no_grad()
    def td_target(
        self, reward: torch.Tensor, next_z: torch.Tensor, done: torch.Tensor
    ) -> torch.Tensor:
        """y = r + gamma * (1 - d) * Q'(s', argmax) (equation 1)."""
        return reward + self.gamma * (1.0 - done) * self.bootstrap_value(next_z)

    @torch.no_grad()
    def bootstrap_value(self, z: torch.Tensor) -> torch.Tensor:
        """Q'(z, argmax): the value a target bootstraps with, (P, B): the target network's
        (or the online one's) max, or with double DQN its value of the online argmax."""
        bootstrap_net = self.target if self.target is not None else self.q
        if self.double_dqn:
            best = self.q(z).argmax(-1, keepdim=True)
            return bootstrap_net(z).gather(-1, best).squeeze(-1)
        return bootstrap_net(z).max(-1).values

    def update(
        self, z: torch.Tensor, action: torch.Tensor, reward: torch.Tensor,
        next_z: torch.Tensor, done: torch.Tensor, agents: Sequence[int],
        target: torch.Tensor | None = None,
    ) -> torch.Tensor:  # fmt: skip
        """One Adam step of each agent in ``agents`` on its mean squared TD error (equation 2)
        over its batch (P, B, ...); returns every agent's loss (P,). ``target``: y given
        (value expansion) instead of equation 1's."""
        y = self.td_target(reward, next_z, done) if target is None else target
        q = self.q(z).gather(-1, action.unsqueeze(-1)).squeeze(-1)
        loss = (q - y).square().mean(-1)
        self.optimizer.zero_grad()
        loss[list(agents)].sum().backward()  # each agent's gradient is its own loss's
        self.optimizer.step(agents)
        chosen = torch.as_tensor(list(agents), dtype=torch.int64)
        self.updates[chosen] += 1
        if self.target is not None:
            due = chosen[self.updates[chosen] % self.target_update_period == 0]
            with torch.no_grad():
                if not len(due):
                    return loss.detach()
                for t, q_param in zip(self.target.parameters(), self.q.parameters(), strict=True):
                    t[due] = q_param[due]
        return loss.detach()
