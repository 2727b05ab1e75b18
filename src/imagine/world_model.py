"""M: the environment model (paper sections III-C, IV and V-B, Environment Model).

Three networks learned online from the real memory:

- the MDN, p(z_{t+1} | z_t, a_t) as a mixture of ``K`` diagonal Gaussians (paper: 5), from 3
  hidden layers of 256 ReLU units with 50% dropout, with three heads: mixture weights (softmax),
  means (linear) and scales (softplus plus a floor, so they stay positive and the likelihood
  finite where the paper's variance head is linear);
- the r-network, the reward from the state alone (3 x 512 ReLU, 50% dropout, log-cosh loss);
- the d-network, whether a state is terminal, from the state alone (2 x 256 ReLU, 50% dropout,
  binary cross-entropy).

The MDN's loss is the negative log-likelihood of equation (6),
-log sum_k pi_k N(z_{t+1}; mu_k, sigma_k^2), computed with log-sum-exp.

:class:`WorldModel` is one agent's M (what a checkpoint holds, what planning and the accuracy
measurements use); :class:`PopulationWorldModel` is the M of P agents trained together (weights
with a leading agent axis, :mod:`imagine.stacked`), each with its own dropout masks, latent
re-sampling noise and Adam state.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from imagine.controller import mlp
from imagine.stacked import PopulationAdam, StackedLinear, StackedMLP, agent_normal

LOG_2PI = math.log(2 * math.pi)


class Mixture(NamedTuple):
    log_pi: torch.Tensor
    """(..., K) log mixture weights."""
    mu: torch.Tensor
    """(..., K, D) component means."""
    sigma: torch.Tensor
    """(..., K, D) component scales (standard deviations)."""


def mixture_from_heads(
    pi: torch.Tensor,
    mu: torch.Tensor,
    sigma: torch.Tensor,
    latent_dim: int,
    min_sigma: float,
    z: torch.Tensor | None = None,
) -> Mixture:
    """The mixture from the three heads' outputs (..., K), (..., K*D), (..., K*D). With the
    current state ``z`` (..., D) given, the mean head predicts each component's change of state
    (residual M): mu_k = z + head_k."""
    shape = (*pi.shape, latent_dim)
    means = mu.view(shape) if z is None else z.unsqueeze(-2) + mu.view(shape)
    return Mixture(F.log_softmax(pi, -1), means, F.softplus(sigma).view(shape) + min_sigma)


def sample_mixture(m: Mixture, generator: torch.Generator) -> torch.Tensor:
    """One draw per row of mixtures (N, ...): a component from the weights, then from its
    Gaussian."""
    k = torch.multinomial(m.log_pi.exp(), 1, generator=generator)  # (N, 1)
    index = k.unsqueeze(-1).expand(-1, 1, m.mu.shape[-1])
    mu, sigma = m.mu.gather(1, index).squeeze(1), m.sigma.gather(1, index).squeeze(1)
    eps = torch.randn(mu.shape, generator=generator, device=mu.device)
    return mu + sigma * eps


def mixture_nll(mixture: Mixture, target: torch.Tensor) -> torch.Tensor:
    """-log sum_k pi_k prod_d N(target_d; mu_kd, sigma_kd^2) (equation 6), per sample."""
    z = (target.unsqueeze(-2) - mixture.mu) / mixture.sigma
    log_normal = -0.5 * (z.square() + LOG_2PI).sum(-1) - mixture.sigma.log().sum(-1)
    return -torch.logsumexp(mixture.log_pi + log_normal, dim=-1)


class MDN(nn.Module):
    """The mixture density network over next latent states."""

    def __init__(
        self,
        latent_dim: int,
        n_actions: int = 6,
        n_components: int = 5,
        hidden: int = 256,
        layers: int = 3,
        dropout: float = 0.5,
        min_sigma: float = 1e-3,
        residual: bool = False,
    ) -> None:
        super().__init__()
        self.latent_dim, self.n_actions, self.n_components = latent_dim, n_actions, n_components
        self.min_sigma, self.residual = min_sigma, residual
        self.body = mlp([latent_dim + n_actions, *[hidden] * layers], dropout)
        self.body.append(nn.ReLU())
        if dropout > 0:
            self.body.append(nn.Dropout(dropout))
        self.pi_head = nn.Linear(hidden, n_components)
        self.mu_head = nn.Linear(hidden, n_components * latent_dim)
        self.sigma_head = nn.Linear(hidden, n_components * latent_dim)

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> Mixture:
        """The mixture for latents (N, D) and integer actions (N,)."""
        h = self.body(torch.cat([z, F.one_hot(action, self.n_actions).to(z)], dim=-1))
        return mixture_from_heads(self.pi_head(h), self.mu_head(h), self.sigma_head(h),
                                  self.latent_dim, self.min_sigma,
                                  z if self.residual else None)  # fmt: skip

    def loss(self, z: torch.Tensor, action: torch.Tensor, next_z: torch.Tensor) -> torch.Tensor:
        return mixture_nll(self(z, action), next_z).mean()

    @torch.no_grad()
    def sample(
        self, z: torch.Tensor, action: torch.Tensor, generator: torch.Generator
    ) -> torch.Tensor:
        """Draw z_{t+1}: a component from the weights, then from its Gaussian."""
        return sample_mixture(self(z, action), generator)

    @torch.no_grad()
    def most_likely(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The mean of the heaviest component: the most likely next state."""
        m = self(z, action)
        k = m.log_pi.argmax(-1)
        return m.mu[torch.arange(len(k), device=k.device), k]


def log_cosh(x: torch.Tensor) -> torch.Tensor:
    """log(cosh(x)), stable for large |x|: |x| + log1p(exp(-2|x|)) - log 2."""
    a = x.abs()
    return a + torch.log1p(torch.exp(-2 * a)) - math.log(2.0)


class RewardNet(nn.Module):
    """The r-network: reward for entering a state, from the state alone."""

    def __init__(self, latent_dim: int, hidden: int = 512, layers: int = 3, dropout: float = 0.5):
        super().__init__()
        self.net = mlp([latent_dim, *[hidden] * layers, 1], dropout)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z).squeeze(-1)

    def loss(self, z: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        return log_cosh(self(z) - reward).mean()


class TerminalNet(nn.Module):
    """The d-network: logit of a state being terminal, from the state alone."""

    def __init__(self, latent_dim: int, hidden: int = 256, layers: int = 2, dropout: float = 0.5):
        super().__init__()
        self.net = mlp([latent_dim, *[hidden] * layers, 1], dropout)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z).squeeze(-1)

    def loss(self, z: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        return F.binary_cross_entropy_with_logits(self(z), done)

    @torch.no_grad()
    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        return self(z) > 0.0


class WorldModel(nn.Module):
    """M: the MDN with its r- and d-networks."""

    def __init__(
        self,
        latent_dim: int,
        n_actions: int = 6,
        n_components: int = 5,
        dropout: float = 0.5,
        reward_hidden: int = 512,
        residual: bool = False,
    ) -> None:
        super().__init__()
        self.dropout = dropout
        self.mdn = MDN(latent_dim, n_actions, n_components, dropout=dropout, residual=residual)
        self.reward = RewardNet(latent_dim, hidden=reward_hidden, dropout=dropout)
        self.terminal = TerminalNet(latent_dim, dropout=dropout)


class PopulationWorldModel(nn.Module):
    """The M of P agents, each starting from its own :class:`WorldModel`. One Adam steps all
    three networks of an agent: their parameters are disjoint, so the gradient of the summed
    loss is each network's own gradient, and the update is the same as with three optimizers."""

    def __init__(self, models: Sequence[WorldModel], lr: float = 1e-3) -> None:
        super().__init__()
        first = models[0]
        self.latent_dim, self.n_actions = first.mdn.latent_dim, first.mdn.n_actions
        self.min_sigma, self.residual = first.mdn.min_sigma, first.mdn.residual
        p = first.dropout
        # registered in WorldModel's parameter order (export_agent relies on it)
        self.mdn_body = StackedMLP([m.mdn.body for m in models], p, activate_last=True)
        self.pi_head = StackedLinear([m.mdn.pi_head for m in models])
        self.mu_head = StackedLinear([m.mdn.mu_head for m in models])
        self.sigma_head = StackedLinear([m.mdn.sigma_head for m in models])
        self.reward = StackedMLP([m.reward.net for m in models], p)
        self.terminal = StackedMLP([m.terminal.net for m in models], p)
        self.optimizer = PopulationAdam(self.parameters(), len(models), lr)

    def heads(
        self, z: torch.Tensor, action: torch.Tensor, generators=None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The MDN heads' outputs for latents (P, N, D) and actions (P, N); dropout with
        ``generators``."""
        x = torch.cat([z, F.one_hot(action, self.n_actions).to(z)], dim=-1)
        h = self.mdn_body(x, generators)
        return self.pi_head(h), self.mu_head(h), self.sigma_head(h)

    @torch.no_grad()
    def sample(
        self, z: torch.Tensor, action: torch.Tensor, generators: Sequence[torch.Generator | None]
    ) -> torch.Tensor:
        """Draw z_{t+1} (P, N, D) for each agent with a generator (zeros for the others).
        The mixture is formed agent by agent: softplus rounds some elements differently at a
        tensor's end, so one agent's few rows must be a tensor of their own to give the numbers
        they give alone."""
        heads = self.heads(z, action)
        out = torch.zeros_like(z)
        for i, generator in enumerate(generators):
            if generator is not None:
                m = mixture_from_heads(*(h[i] for h in heads), self.latent_dim, self.min_sigma,
                                       z[i] if self.residual else None)  # fmt: skip
                out[i] = sample_mixture(m, generator)
        return out

    @torch.no_grad()
    def predict_reward(self, z: torch.Tensor) -> torch.Tensor:
        return self.reward(z).squeeze(-1)

    @torch.no_grad()
    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        return self.terminal(z).squeeze(-1) > 0.0

    @torch.no_grad()
    def mode(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The mean of each row's heaviest component (P, N, D): the most likely next state."""
        m = mixture_from_heads(*self.heads(z, action), self.latent_dim, self.min_sigma,
                               z if self.residual else None)  # fmt: skip
        k = m.log_pi.argmax(-1)[..., None, None].expand(*m.mu.shape[:-2], 1, self.latent_dim)
        return m.mu.gather(-2, k).squeeze(-2)

    def update(
        self,
        batch: dict[str, torch.Tensor],
        generators: Sequence[torch.Generator | None],
        resample: bool = True,
    ) -> dict[str, torch.Tensor]:
        """One update of each network of every agent whose generator is given, on its batch
        (P, B, ...) from the real memory. With ``resample`` latents are drawn from V's
        N(mu, sigma) (the paper's data augmentation); without, M learns from V's means.
        Returns the three losses per agent (P,)."""
        agents = [i for i, g in enumerate(generators) if g is not None]
        if resample:
            z = agent_normal(batch["mu"], batch["sigma"], generators)
            next_z = agent_normal(batch["next_mu"], batch["next_sigma"], generators)
        else:
            z, next_z = batch["mu"], batch["next_mu"]
        mixture = mixture_from_heads(*self.heads(z, batch["action"], generators),
                                     self.latent_dim, self.min_sigma,
                                     z if self.residual else None)  # fmt: skip
        reward = self.reward(next_z, generators).squeeze(-1)
        terminal = self.terminal(next_z, generators).squeeze(-1)
        losses = {
            "mdn": mixture_nll(mixture, next_z).mean(-1),
            "reward": log_cosh(reward - batch["reward"]).mean(-1),
            "terminal": F.binary_cross_entropy_with_logits(
                terminal, batch["done"], reduction="none"
            ).mean(-1),
        }
        self.optimizer.zero_grad()
        sum(loss[agents].sum() for loss in losses.values()).backward()
        self.optimizer.step(agents)
        return {name: loss.detach() for name, loss in losses.items()}
