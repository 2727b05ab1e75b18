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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from imagine.controller import adam, mlp

LOG_2PI = math.log(2 * math.pi)


class Mixture(NamedTuple):
    log_pi: torch.Tensor
    """(N, K) log mixture weights."""
    mu: torch.Tensor
    """(N, K, D) component means."""
    sigma: torch.Tensor
    """(N, K, D) component scales (standard deviations)."""


def mixture_nll(mixture: Mixture, target: torch.Tensor) -> torch.Tensor:
    """-log sum_k pi_k prod_d N(target_d; mu_kd, sigma_kd^2), per sample (N,)."""
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
    ) -> None:
        super().__init__()
        self.latent_dim, self.n_actions, self.n_components = latent_dim, n_actions, n_components
        self.min_sigma = min_sigma
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
        shape = (*z.shape[:-1], self.n_components, self.latent_dim)
        sigma = F.softplus(self.sigma_head(h)).view(shape) + self.min_sigma
        return Mixture(F.log_softmax(self.pi_head(h), -1), self.mu_head(h).view(shape), sigma)

    def loss(self, z: torch.Tensor, action: torch.Tensor, next_z: torch.Tensor) -> torch.Tensor:
        return mixture_nll(self(z, action), next_z).mean()

    @torch.no_grad()
    def sample(
        self, z: torch.Tensor, action: torch.Tensor, generator: torch.Generator
    ) -> torch.Tensor:
        """Draw z_{t+1}: a component from the weights, then from its Gaussian."""
        m = self(z, action)
        k = torch.multinomial(m.log_pi.exp(), 1, generator=generator)  # (N, 1)
        index = k.unsqueeze(-1).expand(-1, 1, self.latent_dim)
        mu, sigma = m.mu.gather(1, index).squeeze(1), m.sigma.gather(1, index).squeeze(1)
        eps = torch.randn(mu.shape, generator=generator, device=mu.device)
        return mu + sigma * eps

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
    """M: the MDN with its r- and d-networks. One Adam steps all three: their parameters are
    disjoint, so the gradient of the summed loss is each network's own gradient, and the update
    is the same as with three optimizers, in one fused step."""

    def __init__(
        self,
        latent_dim: int,
        n_actions: int = 6,
        n_components: int = 5,
        dropout: float = 0.5,
        lr: float = 1e-3,
        reward_hidden: int = 512,
    ) -> None:
        super().__init__()
        self.mdn = MDN(latent_dim, n_actions, n_components, dropout=dropout)
        self.reward = RewardNet(latent_dim, hidden=reward_hidden, dropout=dropout)
        self.terminal = TerminalNet(latent_dim, dropout=dropout)
        self.optimizer = adam(self.parameters(), lr)

    def update(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator
    ) -> dict[str, float]:
        """One update of each network on a batch from the real memory; latents are re-sampled
        from V's N(mu, sigma) (the paper's data augmentation). Returns the three losses."""

        def draw(mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
            return mu + sigma * torch.randn(mu.shape, generator=generator, device=mu.device)

        z, next_z = draw(batch["mu"], batch["sigma"]), draw(batch["next_mu"], batch["next_sigma"])
        if not self.training:  # a recursive call over every module: skip it when it is a no-op
            self.train()
        losses = {
            "mdn": self.mdn.loss(z, batch["action"], next_z),
            "reward": self.reward.loss(next_z, batch["reward"]),
            "terminal": self.terminal.loss(next_z, batch["done"]),
        }
        self.optimizer.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        self.optimizer.step()
        return {name: float(loss.detach()) for name, loss in losses.items()}
