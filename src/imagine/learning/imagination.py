"""Imagined rollouts: M run in closed loop like an environment (paper section IV; Algorithm 1,
lines 17-18).

``I_B`` rollouts start from the current real latent state (each a sample of V's N(mu, sigma)),
act with C epsilon-greedily, draw the next state from the MDN and feed it back, take the reward
from the r-network and end a rollout where the d-network says terminal, after at most ``I_D``
steps. M imagines without dropout.

Every agent of a population imagines at once; an agent draws from its own generator, and only
while one of its rollouts is still going, so its rollouts are those it would imagine alone.

With an ensemble of K MDNs per agent (``model_ensemble``), each rollout follows a member drawn
uniformly at each step (PETS's TS1 propagation, Chua et al. 2018; MBPO, Janner et al. 2019),
so the members' differences stay in what C is handed instead of being averaged away (the mean
of two modes that name different macrostates names neither). Every imagined transition carries
the members' disagreement about it, from the K modes m_k of its next state:

    disagreement = (1 / (K (K - 1))) sum_{j != k} || m_j - m_k ||_2  /  s,

s the mean of V's posterior sigma over its active dimensions at the rollout's start
(:func:`posterior_scale`): how far apart two members put the next state, on average, in units
of V's own uncertainty about a state; 0 with one member or members that agree. A detector of
wrong transitions that needs no labels: ``imagine evaluate`` reports its AUROC.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from imagine.models.controller import PopulationController
from imagine.models.stacked import agent_normal
from imagine.models.world_model import PopulationWorldModel, Prediction

FIELDS = ("z", "action", "next_z", "reward", "done", "disagreement", "rollout", "step")
"""What a rollout hands back per transition: M_I's fields, the members' disagreement, and
which of the agent's rollouts it belongs to and its step in it (what a gate needs,
:mod:`imagine.learning.gate`)."""

ACTIVE_SIGMA = 0.5
"""A latent dimension V uses has a posterior sigma well below the prior's 1; a collapsed one
keeps sigma near 1 and carries no information (:mod:`imagine.envs.gesture_puzzle.vision_report`)."""


def posterior_scale(sigma: torch.Tensor) -> torch.Tensor:
    """The unit of disagreement for posteriors (..., D): the mean of sigma over the active
    dimensions (sigma < :data:`ACTIVE_SIGMA`), over all when none is; (...)."""
    active = sigma < ACTIVE_SIGMA
    count = active.sum(-1)
    mean_active = (sigma * active).sum(-1) / count.clamp(min=1)
    return torch.where(count > 0, mean_active, sigma.mean(-1)).clamp(min=1e-6)


@torch.no_grad()
def imagine_rollouts(
    model: PopulationWorldModel,
    controller: PopulationController,
    mu: torch.Tensor,
    sigma: torch.Tensor,
    breadth: int,
    depth: int,
    eps: Sequence[float],
    generators: Sequence[torch.Generator | None],
    draw: str = "sample",
    scale: torch.Tensor | None = None,
    actions: str = "policy",
) -> list[dict[str, torch.Tensor] | None]:
    """For each agent i with a generator: the transitions ``(z, action, next_z, reward, done,
    disagreement, rollout, step)`` of ``breadth`` rollouts of up to ``depth`` steps from its
    latent posterior ``N(mu[i], sigma[i])`` (mu, sigma: (P, latent_dim)), or of one rollout
    from each of ``N(mu[i, b], sigma[i, b])`` (mu, sigma: (P, B, latent_dim)), in the order
    imagined (step by step, rollouts in order within a step);
    None for agents without one. ``draw``: each next state a sample of M's mixture (the
    paper; :func:`~imagine.models.world_model.sample_mixture`), or its mode (the
    mean of the heaviest component). ``scale``: the unit of
    disagreement, per agent (P,) or rollout (P, B); default :func:`posterior_scale` of
    ``sigma`` (pass V's own when ``sigma`` is not V's). ``actions``: policy (C acts
    epsilon-greedily, the paper) or all (:func:`every_action`: one step of each action from
    each start, ``depth`` ignored)."""
    if mu.dim() == 2:
        mu, sigma = mu.unsqueeze(1), sigma.unsqueeze(1)
    else:
        breadth = mu.shape[1]
    P, _, D = mu.shape
    shape = (P, breadth, D)
    unit = posterior_scale(sigma) if scale is None else scale.view(P, -1)
    unit = unit.expand(P, breadth)
    z = agent_normal(mu.expand(shape), sigma.expand(shape), generators)
    rollout = torch.arange(breadth, device=mu.device).expand(P, breadth)
    fixed = None
    if actions == "all":
        z, unit, rollout, fixed = every_action(z, unit, rollout, controller.n_actions)
        breadth, depth = z.shape[1], 1
    going = torch.tensor([g is not None for g in generators], device=mu.device)
    alive = going.unsqueeze(1).expand(P, breadth).clone()
    steps: list[tuple[torch.Tensor, ...]] = []  # each step's (P, breadth, ...) values
    kept: list[torch.Tensor] = []  # which rollouts were alive at each step
    for t in range(depth):
        flags = going.tolist()  # one read of the device per depth step
        drawing = [g if flags[i] else None for i, g in enumerate(generators)]
        action = controller.act(z, eps, drawing) if fixed is None else fixed
        next_z, spread = model.predict(z, action, drawing, draw)
        done = model.is_terminal(next_z)
        reward = model.predict_reward(next_z)
        steps.append((z, action, next_z, reward, done.float(), spread / unit, rollout,
                      torch.full_like(rollout, t)))  # fmt: skip
        kept.append(alive.clone())
        alive &= ~done
        going &= alive.any(-1)
        if not going.any():
            break
        z = next_z
    mask = torch.stack(kept)  # (T, P, breadth)
    stacked = [torch.stack(values) for values in zip(*steps, strict=True)]
    return [
        None
        if generator is None
        else {key: value[:, i][mask[:, i]] for key, value in zip(FIELDS, stacked, strict=True)}
        for i, generator in enumerate(generators)
    ]


def actions_at(config, episode: int) -> str:
    """What an agent's imagined rollouts do at ``episode`` (``imagination_actions``, until
    ``imagination_actions_until`` switches every action's backups to the paper's policy
    rollouts)."""
    until = config.imagination_actions_until
    return "policy" if until and episode >= until else config.imagination_actions


def every_action(
    z: torch.Tensor, unit: torch.Tensor, rollout: torch.Tensor, n_actions: int
) -> tuple[torch.Tensor, ...]:
    """Imagination over every action (``imagination_actions: all``): each start latent of
    ``z`` (P, B, D) repeated once per action, with its unit of disagreement, and the actions
    0..A-1 beside each: (P, B * A, ...), each (start, action) a one-step rollout of its own
    (index b * A + a; so a ``stop`` gate drops only the transitions over its threshold, as
    ``mask`` does, not a start's whole backup). One step of each is a full backup of
    the start state through M (Sutton and Barto's expected update, with M's draw for the
    expectation): C learns the value of the actions its behaviour did not take there, which no
    replayed transition holds (van Hasselt et al. 2019: a model used only for transitions from
    observed states with the actions taken there adds little to replay)."""
    P, B, _ = z.shape
    action = torch.arange(n_actions, device=z.device).repeat(B).expand(P, B * n_actions)
    own = rollout.repeat_interleave(n_actions, 1) * n_actions + action
    return z.repeat_interleave(n_actions, 1), unit.repeat_interleave(n_actions, 1), own, action


class SplitModel:
    """Imagination's next state from one M, its reward from another and its end from a third:
    the diagnostics ``imagination_model: true_reward`` (the learned M's next state, the rules'
    reward and end), ``true_end`` (the learned next state and reward, the rules' end) and
    ``true_state`` (the rules' next state as its mean latent, the learned r- and d-networks),
    which tell which part of a learned M costs the agent what."""

    def __init__(self, state_from, reward_from, end_from=None) -> None:
        self.state_from, self.reward_from = state_from, reward_from
        self.end_from = reward_from if end_from is None else end_from

    def predict(self, z, action, generators=(), draw: str = "mode") -> Prediction:
        return self.state_from.predict(z, action, generators, draw)

    def is_terminal(self, z: torch.Tensor) -> torch.Tensor:
        return self.end_from.is_terminal(z)

    def predict_reward(self, z: torch.Tensor) -> torch.Tensor:
        return self.reward_from.predict_reward(z)
