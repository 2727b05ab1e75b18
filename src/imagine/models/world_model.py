"""M: the environment model (paper sections III-C, IV and V-B, Environment Model).

Three networks learned online from the real memory:

- the MDN, p(z_{t+1} | z_t, a_t) as a mixture of ``K`` diagonal Gaussians (paper: 5), from 3
  hidden layers of 256 ReLU units with 50% dropout, with three heads: mixture weights (softmax),
  means (linear) and scales (softplus plus a floor, so they stay positive and the likelihood
  finite where the paper's variance head is linear);
- the r-network, the reward from the state alone (3 x 512 ReLU, 50% dropout, log-cosh loss);
- the d-network, whether a state is terminal, from the state alone (2 x 256 ReLU, 50% dropout,
  binary cross-entropy).

The MDN's loss is the negative log-likelihood of equation (5),
-log sum_k pi_k N(z_{t+1}; mu_k, sigma_k^2), computed with log-sum-exp.

:class:`WorldModel` is one agent's M (what a checkpoint holds, what planning and the accuracy
measurements use); :class:`PopulationWorldModel` is the M of P agents trained together (weights
with a leading agent axis, :mod:`imagine.models.stacked`), each with its own dropout masks, latent
re-sampling noise and Adam state.

An agent's M may hold an ensemble of K MDNs (``model_ensemble``; PETS, Chua et al. 2018, and
MBPO, Janner et al. 2019): K independently initialized members, each trained on its own
bootstrap batch, whose disagreement about a next state (:func:`members_spread`) says where M
does not know. The paper's M is K = 1.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from imagine.models.controller import mlp
from imagine.models.stacked import (
    PopulationAdam,
    StackedLinear,
    StackedMLP,
    agent_normal,
    export_agent,
    import_agent,
)

LOG_2PI = math.log(2 * math.pi)


class Mixture(NamedTuple):
    log_pi: torch.Tensor
    """(..., K) log mixture weights."""
    mu: torch.Tensor
    """(..., K, D) component means."""
    sigma: torch.Tensor
    """(..., K, D) component scales (standard deviations) of diagonal Gaussians."""


def mixture_from_heads(
    pi: torch.Tensor,
    mu: torch.Tensor,
    sigma: torch.Tensor,
    latent_dim: int,
    min_sigma: float,
    z: torch.Tensor | None = None,
) -> Mixture:
    """The mixture from the heads' outputs (..., K), (..., K*D), (..., K*D). With the current
    state ``z`` (..., D) given, the mean head predicts each component's change of state
    (residual M): mu_k = z + head_k."""
    shape = (*pi.shape, latent_dim)
    means = mu.view(shape) if z is None else z.unsqueeze(-2) + mu.view(shape)
    return Mixture(F.log_softmax(pi, -1), means, F.softplus(sigma).view(shape) + min_sigma)


def component_log_normal(m: Mixture, x: torch.Tensor) -> torch.Tensor:
    """log N(x; mu_k, diag(sigma_k^2)) of each component (..., K) for points x (..., D):
    -(|(x - mu_k) / sigma_k|^2 + D log 2 pi) / 2 - sum_d log sigma_kd."""
    white = (x.unsqueeze(-2) - m.mu) / m.sigma
    return -0.5 * (white.square() + LOG_2PI).sum(-1) - m.sigma.log().sum(-1)


def sample_mixture(
    m: Mixture,
    generator: torch.Generator,
    component: str = "weights",
    spread: bool = True,
) -> torch.Tensor:
    """One draw per row of mixtures (N, ...): a component from the weights (or, with
    ``component="heaviest"``, the heaviest one), then a draw from its Gaussian (without
    ``spread``: its mean)."""
    if component == "heaviest":
        k = m.log_pi.argmax(-1, keepdim=True)  # (N, 1)
    else:
        k = torch.multinomial(m.log_pi.exp(), 1, generator=generator)  # (N, 1)
    D = m.mu.shape[-1]
    index = k.unsqueeze(-1).expand(-1, 1, D)
    mu, sigma = m.mu.gather(1, index).squeeze(1), m.sigma.gather(1, index).squeeze(1)
    if not spread:
        return mu
    eps = torch.randn(mu.shape, generator=generator, device=mu.device)
    return mu + sigma * eps


def mixture_nll(mixture: Mixture, target: torch.Tensor) -> torch.Tensor:
    """-log sum_k pi_k prod_d N(target_d; mu_kd, sigma_kd^2) (equation 5), per sample."""
    return -torch.logsumexp(mixture.log_pi + component_log_normal(mixture, target), dim=-1)


class MDN(nn.Module):
    """The mixture density network over next latent states (equation 5's p(z_{t+1} | z_t, a_t))."""

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
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generator: torch.Generator,
    ) -> torch.Tensor:
        """Draw z_{t+1}: a component from the weights, then from its Gaussian
        (:func:`sample_mixture`)."""
        return sample_mixture(self(z, action), generator)

    @torch.no_grad()
    def explain(
        self, z: torch.Tensor, action: torch.Tensor, observed: torch.Tensor
    ) -> torch.Tensor:
        """The mean of the component that best explains the ``observed`` next latent
        (:func:`responsible_mean`)."""
        return responsible_mean(self(z, action), observed)

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


def squared(x: torch.Tensor) -> torch.Tensor:
    """x^2: the mean squared error's term. Unlike log-cosh, whose gradient is at most 1, its
    gradient grows with the error, so r's few large errors (an unseen +50) dominate a batch."""
    return x.square()


REWARD_LOSSES = {"logcosh": log_cosh, "mse": squared}
"""The r-network's losses per transition (``AgentConfig.reward_loss``; the paper's log-cosh)."""


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
    """M: the MDN with its r- and d-networks; with ``ensemble`` K > 1, K MDNs (PETS's
    ensemble; r and d stay single). The first is ``mdn``, the others ``more_mdns``, made after
    r and d: a one-member M has the state dict and the initial weights it always had, and
    member 0 of an ensemble starts as that M's MDN."""

    def __init__(
        self,
        latent_dim: int,
        n_actions: int = 6,
        n_components: int = 5,
        dropout: float = 0.5,
        reward_hidden: int = 512,
        residual: bool = False,
        ensemble: int = 1,
        reward_dropout: float | None = None,
        terminal_hidden: int = 256,
        hidden: int = 256,
    ) -> None:
        super().__init__()
        self.dropout = dropout
        self.reward_dropout = dropout if reward_dropout is None else reward_dropout

        def mdn() -> MDN:
            return MDN(latent_dim, n_actions, n_components, hidden, dropout=dropout,
                       residual=residual)  # fmt: skip

        self.mdn = mdn()
        self.reward = RewardNet(latent_dim, hidden=reward_hidden, dropout=self.reward_dropout)
        self.terminal = TerminalNet(latent_dim, hidden=terminal_hidden, dropout=self.reward_dropout)
        self.more_mdns = nn.ModuleList(mdn() for _ in range(ensemble - 1))

    @property
    def members(self) -> list[MDN]:
        """The K MDNs, ``mdn`` first."""
        return [self.mdn, *self.more_mdns]

    def most_likely(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """M's point prediction of the next state, what the accuracy, generalization and
        planning tests read: the MDN's most likely next state (:meth:`MDN.most_likely`); with
        an ensemble, the mean of the members' most likely next states, (1 / K) sum_k mode_k
        (the ensemble's prediction, as PETS and MBPO average their members;
        docs/research/model-trust.md: it names the right macrostate more often than any one
        member, most of all from states M never trained on)."""
        if not self.more_mdns:
            return self.mdn.most_likely(z, action)
        return torch.stack([mdn.most_likely(z, action) for mdn in self.members]).mean(0)


def mixture_mode(m: Mixture) -> torch.Tensor:
    """The mean of each mixture's heaviest component (..., D): its most likely point."""
    k = m.log_pi.argmax(-1)[..., None, None].expand(*m.mu.shape[:-2], 1, m.mu.shape[-1])
    return m.mu.gather(-2, k).squeeze(-2)


def responsible_mean(m: Mixture, observed: torch.Tensor) -> torch.Tensor:
    """The mean of each mixture's component that best explains ``observed`` (..., D): the one
    of highest posterior responsibility, argmax_k log pi_k + log N(observed; mu_k, sigma_k^2)
    (the terms of equation 5). Where one outcome dominates it is the mode; where M knows
    several (a hand that may move), the one the observation shows."""
    log_joint = m.log_pi + component_log_normal(m, observed)
    k = log_joint.argmax(-1)[..., None, None].expand(*m.mu.shape[:-2], 1, m.mu.shape[-1])
    return m.mu.gather(-2, k).squeeze(-2)


def members_spread(modes: torch.Tensor) -> torch.Tensor:
    """The members' disagreement about each row, from their modes (..., K, N, D): the mean
    Euclidean distance between two members' modes, (1 / (K (K - 1))) sum_{j != k}
    ||m_j - m_k||_2, (..., N); 0 for one member. Pairwise rather than to the members' mean
    mode, whose rounding would leave identical members a little apart: here they are exactly
    0 apart."""
    K = modes.shape[-3]
    if K == 1:
        return modes.new_zeros(modes.shape[:-3] + modes.shape[-2:-1])
    pairs = (modes.unsqueeze(-3) - modes.unsqueeze(-4)).norm(dim=-1)  # (..., K, K, N)
    return pairs.sum((-3, -2)) / (K * (K - 1))


class StackedMDN(nn.Module):
    """Many MDNs of one architecture as one stack (:mod:`imagine.models.stacked`): the body and
    three heads of row r are those of ``mdns[r]``."""

    def __init__(self, mdns: Sequence[MDN], dropout: float) -> None:
        super().__init__()
        # registered in MDN's parameter order (export_agent relies on it)
        self.body = StackedMLP([m.body for m in mdns], dropout, activate_last=True)
        self.pi_head = StackedLinear([m.pi_head for m in mdns])
        self.mu_head = StackedLinear([m.mu_head for m in mdns])
        self.sigma_head = StackedLinear([m.sigma_head for m in mdns])

    def forward(
        self, x: torch.Tensor, generators: Sequence[torch.Generator | None] | None = None
    ) -> tuple[torch.Tensor, ...]:
        """The heads' outputs for inputs (R, N, in) (one row of networks each); dropout with
        ``generators`` (one per row)."""
        h = self.body(x, generators)
        return self.pi_head(h), self.mu_head(h), self.sigma_head(h)


_DRAWS: dict[str, dict[str, Any]] = {
    "sample": {"component": "weights"},
    "component": {"component": "heaviest"},
    "outcome": {"component": "weights", "spread": False},
}
""":func:`sample_mixture`'s arguments for each draw of imagination (``imagination_draw``): which
component it takes, and whether it draws from its Gaussian or takes its mean."""


class Prediction(NamedTuple):
    next_z: torch.Tensor
    """(P, N, D) the imagined next states."""
    spread: torch.Tensor
    """(P, N) the members' disagreement about them (:func:`members_spread`; 0 for K = 1)."""


class PopulationWorldModel(nn.Module):
    """The M of P agents, each starting from its own :class:`WorldModel`. One Adam steps all
    three networks of an agent: their parameters are disjoint, so the gradient of the summed
    loss is each network's own gradient, and the update is the same as with three optimizers.

    An agent's K MDN members are rows ``i * K + k`` of one stack of P * K MDNs (agent-major),
    so an ensemble costs larger batched products, not more kernels; r and d have P rows.
    Members are independent networks (PETS, Chua et al. 2018): each its own initialization,
    its own bootstrap batch of M_R in :meth:`update` and its own dropout masks."""

    def __init__(
        self, models: Sequence[WorldModel], lr: float = 1e-3, reward_loss: str = "logcosh"
    ) -> None:
        super().__init__()
        self.reward_loss = REWARD_LOSSES[reward_loss]
        first = models[0]
        self.latent_dim, self.n_actions = first.mdn.latent_dim, first.mdn.n_actions
        self.min_sigma, self.residual = first.mdn.min_sigma, first.mdn.residual
        self.ensemble = K = len(first.members)
        if any(len(m.members) != K for m in models):
            raise ValueError("every agent's M needs the same number of MDN members")
        p = first.dropout
        # registered in the order a one-member WorldModel registers them (optimizer indices)
        self.mdn = StackedMDN([mdn for m in models for mdn in m.members], p)
        self.reward = StackedMLP([m.reward.net for m in models], first.reward_dropout)
        self.terminal = StackedMLP([m.terminal.net for m in models], first.reward_dropout)
        n_mdn = len(list(self.mdn.parameters()))
        n_rest = len(list(self.parameters())) - n_mdn
        self.optimizer = PopulationAdam(
            self.parameters(), len(models), lr, members=[K] * n_mdn + [1] * n_rest
        )

    # --- the member axis ----------------------------------------------------------------------

    def _each_member(self, x: torch.Tensor) -> torch.Tensor:
        """Agents' rows (P, N, ...) given to each of their members: (P * K, N, ...)."""
        return x if self.ensemble == 1 else x.repeat_interleave(self.ensemble, 0)

    def _member_rows(self, x: torch.Tensor) -> torch.Tensor:
        """Agents' K batches one after the other (P, K * B, ...) as members' rows
        (P * K, B, ...): member k gets the k-th."""
        P, KB = x.shape[:2]
        return x.reshape(P * self.ensemble, KB // self.ensemble, *x.shape[2:])

    def _member_generators(
        self, generators: Sequence[torch.Generator | None] | None
    ) -> list[torch.Generator | None] | None:
        """Each agent's generator once per member: its members' dropout masks are drawn
        from it one after the other."""
        if generators is None:
            return None
        return [g for g in generators for _ in range(self.ensemble)]

    def _heads(
        self, z: torch.Tensor, action: torch.Tensor, generators=None
    ) -> tuple[torch.Tensor, ...]:
        """The MDN heads for members' rows: latents (P * K, N, D), actions (P * K, N)."""
        x = torch.cat([z, F.one_hot(action, self.n_actions).to(z)], dim=-1)
        return self.mdn(x, self._member_generators(generators))

    def _mixture(self, heads: Sequence[torch.Tensor], z: torch.Tensor) -> Mixture:
        """The mixtures from heads' outputs; ``z``: the rows' states, for a residual M."""
        return mixture_from_heads(*heads, self.latent_dim, self.min_sigma,
                                  z if self.residual else None)  # fmt: skip

    @torch.no_grad()
    def member_modes(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Every member's most likely next state for latents (P, N, D) and actions (P, N):
        (P, K, N, D)."""
        zs = self._each_member(z)
        modes = mixture_mode(self._mixture(self._heads(zs, self._each_member(action)), zs))
        return modes.view(z.shape[0], self.ensemble, *z.shape[1:])

    @torch.no_grad()
    def mean_mode(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The members' mean most likely next state (P, N, D), (1 / K) sum_k mode_k: each
        agent's :meth:`WorldModel.most_likely`."""
        return self.member_modes(z, action).mean(1)

    @torch.no_grad()
    def member_paths(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each member's most likely next state on its own rows: latents (P, K, N, D) and
        actions (P, K, N), row [i, k] for member k of agent i; (P, K, N, D). K rollouts, one
        per member (STEVE's; :mod:`imagine.learning.value_expansion`)."""
        P, K, N, D = z.shape
        zs = z.reshape(P * K, N, D)
        heads = self._heads(zs, action.reshape(P * K, N))
        return mixture_mode(self._mixture(heads, zs)).view(P, K, N, D)

    def _draw_members(
        self, rows: int, generators: Sequence[torch.Generator | None], device: torch.device
    ) -> torch.Tensor:
        """(P, rows): the member each row follows, uniform from each agent's generator (PETS's
        TS1 and MBPO: a member per transition); member 0 for agents without one."""
        member = torch.zeros(len(generators), rows, dtype=torch.int64, device=device)
        for i, generator in enumerate(generators):
            if generator is not None:
                member[i] = torch.randint(self.ensemble, (rows,), generator=generator,
                                          device=generator.device).to(device)  # fmt: skip
        return member

    # --- imagination ----------------------------------------------------------------------------

    @torch.no_grad()
    def predict(
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generators: Sequence[torch.Generator | None],
        draw: str = "sample",
    ) -> Prediction:
        """The next state of rows (P, N, D) for each agent with a generator (zeros for the
        others with the random draws; with ``mode`` every agent gets its mode, of member 0 when
        K > 1), as imagination draws it: a sample of M's mixture, its
        ``mode``, a draw from its heaviest component's Gaussian (``component``) or the mean of
        a component drawn by its weight (``outcome``) (:func:`sample_mixture`); with K > 1
        members, each row from the member drawn for it (:meth:`_draw_members`). With the
        members' disagreement about the row."""
        if self.ensemble == 1:
            next_z = self._mode_one(z, action) if draw == "mode" else self._sample_one(
                z, action, generators, draw)  # fmt: skip
            return Prediction(next_z, torch.zeros(z.shape[:-1], device=z.device))
        P, N, D = z.shape
        zs, actions = self._each_member(z), self._each_member(action)
        heads = self._heads(zs, actions)
        modes = mixture_mode(self._mixture(heads, zs)).view(P, self.ensemble, N, D)
        member = self._draw_members(N, generators, z.device)
        if draw == "mode":
            next_z = modes.gather(1, member[:, None, :, None].expand(P, 1, N, D)).squeeze(1)
        else:
            per_member = [h.view(P, self.ensemble, N, -1) for h in heads]
            rows = torch.arange(N, device=z.device)
            next_z = torch.zeros_like(z)
            for i, generator in enumerate(generators):
                if generator is not None:
                    chosen = [h[i, member[i], rows] for h in per_member]
                    next_z[i] = sample_mixture(self._mixture(chosen, z[i]), generator,
                                               **_DRAWS[draw])  # fmt: skip
        return Prediction(next_z, members_spread(modes))

    @torch.no_grad()
    def sample(
        self, z: torch.Tensor, action: torch.Tensor, generators: Sequence[torch.Generator | None]
    ) -> torch.Tensor:
        """Draw z_{t+1} (P, N, D) for each agent with a generator (zeros for the others), from
        a member drawn per row when K > 1."""
        return self.predict(z, action, generators, "sample").next_z

    @torch.no_grad()
    def mode(
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generators: Sequence[torch.Generator | None] | None = None,
    ) -> torch.Tensor:
        """The mean of each row's heaviest component (P, N, D): the most likely next state;
        with K > 1, of a member drawn per row from ``generators`` (member 0 without)."""
        if self.ensemble == 1:
            return self._mode_one(z, action)
        return self.predict(z, action, generators or [None] * len(z), "mode").next_z

    def _sample_one(
        self,
        z: torch.Tensor,
        action: torch.Tensor,
        generators: Sequence[torch.Generator | None],
        draw: str = "sample",
    ) -> torch.Tensor:
        """:meth:`sample` of a one-member M. The mixture is formed agent by agent: softplus
        rounds some elements differently at a tensor's end, so one agent's few rows must be a
        tensor of their own to give the numbers they give alone."""
        heads = self._heads(z, action)
        out = torch.zeros_like(z)
        for i, generator in enumerate(generators):
            if generator is not None:
                out[i] = sample_mixture(self._mixture([h[i] for h in heads], z[i]), generator,
                                        **_DRAWS[draw])  # fmt: skip
        return out

    @torch.no_grad()
    def explain(self, z: torch.Tensor, action: torch.Tensor, observed: torch.Tensor):
        """For latents, actions and observed next latents (P, N, ...): the mean of the
        component of each row's mixture that best explains its observation
        (:func:`responsible_mean`), of member 0 when K > 1; (P, N, D)."""
        if self.ensemble > 1:
            P, N, D = z.shape
            zs = self._each_member(z)
            m = self._mixture(self._heads(zs, self._each_member(action)), zs)
            means = responsible_mean(m, self._each_member(observed)).view(P, self.ensemble, N, D)
            return means[:, 0]
        return responsible_mean(self._mixture(self._heads(z, action), z), observed)

    def _mode_one(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return mixture_mode(self._mixture(self._heads(z, action), z))

    @torch.no_grad()
    def predict_reward(self, z: torch.Tensor) -> torch.Tensor:
        return self.reward(z).squeeze(-1)

    @torch.no_grad()
    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        return self.terminal(z).squeeze(-1) > 0.0

    def update(
        self,
        batch: dict[str, torch.Tensor],
        generators: Sequence[torch.Generator | None],
        resample: bool = True,
        mdn: bool = True,
        terminal_weight: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """One update of each network of every agent whose generator is given, on its batch
        (P, K * B, ...) from the real memory: K bootstrap batches of B one after the other,
        member k of the MDN learning from the k-th (PETS), r and d from the first. With
        ``resample`` latents are drawn from V's N(mu, sigma) (the paper's data augmentation);
        without, M learns from V's means. Returns the three losses per agent (P,), the MDN's
        averaged over its members (each member's gradient is that of its own loss). Without
        ``mdn``, r and d alone (a batch (P, B, ...); ``reward_updates``). ``terminal_weight``
        (P,): the weight of each agent's terminal transitions in d's loss (1: none)."""
        agents = [i for i, g in enumerate(generators) if g is not None]
        if mdn:  # z drawn before next_z: the random streams of the paper's update
            z = agent_normal(batch["mu"], batch["sigma"], generators) if resample else batch["mu"]
        if resample:
            next_z = agent_normal(batch["next_mu"], batch["next_sigma"], generators)
        else:
            next_z = batch["next_mu"]
        losses = {}
        if mdn:
            member_z, member_next = self._member_rows(z), self._member_rows(next_z)
            member_action = self._member_rows(batch["action"])
            heads = self._heads(member_z, member_action, generators)
            nll = mixture_nll(self._mixture(heads, member_z), member_next).mean(-1)
            losses["mdn"] = nll.view(len(generators), self.ensemble)  # (P, K)
        first = slice(0, batch["action"].shape[1] // (self.ensemble if mdn else 1))  # member 0's
        reward = self.reward(next_z[:, first], generators).squeeze(-1)
        terminal = self.terminal(next_z[:, first], generators).squeeze(-1)
        losses["reward"] = self.reward_loss(reward - batch["reward"][:, first]).mean(-1)
        weight = None if terminal_weight is None else terminal_weight.unsqueeze(-1)
        losses["terminal"] = F.binary_cross_entropy_with_logits(
            terminal, batch["done"][:, first], reduction="none", pos_weight=weight
        ).mean(-1)
        self.optimizer.zero_grad()
        total = sum(loss[agents].sum() for loss in losses.values())
        total.backward()
        self.optimizer.step(agents)
        if mdn:
            nll = losses["mdn"]
            losses["mdn"] = nll.mean(-1) if self.ensemble > 1 else nll[:, 0]
        return {name: loss.detach() for name, loss in losses.items()}

    # --- one agent's M as a single-agent module ---------------------------------------------------

    @torch.no_grad()
    def export_agent(self, agent: int, model: WorldModel) -> WorldModel:
        """Copy agent ``agent``'s networks into a single-agent M (same K); returns it."""
        for k, mdn in enumerate(model.members):
            export_agent(self.mdn, agent * self.ensemble + k, mdn)
        export_agent(self.reward, agent, model.reward.net)
        export_agent(self.terminal, agent, model.terminal.net)
        return model

    @torch.no_grad()
    def import_agent(self, agent: int, model: WorldModel) -> None:
        """Copy a single-agent M's networks (same K) into agent ``agent``'s rows."""
        for k, mdn in enumerate(model.members):
            import_agent(self.mdn, agent * self.ensemble + k, mdn)
        import_agent(self.reward, agent, model.reward.net)
        import_agent(self.terminal, agent, model.terminal.net)
