"""Imagined rollouts: M run in closed loop like an environment (paper section IV; Algorithm 1,
lines 17-18).

``I_B`` rollouts start from the current real latent state (each a sample of V's N(mu, sigma)),
act with C epsilon-greedily, draw the next state from the MDN and feed it back, take the reward
from the r-network and end a rollout where the d-network says terminal, after at most ``I_D``
steps. M imagines without dropout.

Every agent of a population imagines at once; an agent draws from its own generator, and only
while one of its rollouts is still going, so its rollouts are those it would imagine alone.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from imagine.controller import PopulationController
from imagine.stacked import agent_normal
from imagine.world_model import PopulationWorldModel

FIELDS = ("z", "action", "next_z", "reward", "done")


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
) -> list[dict[str, torch.Tensor] | None]:
    """For each agent i with a generator: the transitions ``(z, action, next_z, reward, done)``
    of ``breadth`` rollouts of up to ``depth`` steps from its latent posterior
    ``N(mu[i], sigma[i])`` (mu, sigma: (P, latent_dim)), or of one rollout from each of
    ``N(mu[i, b], sigma[i, b])`` (mu, sigma: (P, B, latent_dim)), in the order imagined;
    None for agents without one. ``draw``: each next state a sample of M's mixture (the
    paper), or its mode (the mean of the heaviest component)."""
    if mu.dim() == 2:
        mu, sigma = mu.unsqueeze(1), sigma.unsqueeze(1)
    else:
        breadth = mu.shape[1]
    P, _, D = mu.shape
    shape = (P, breadth, D)
    z = agent_normal(mu.expand(shape), sigma.expand(shape), generators)
    going = torch.tensor([g is not None for g in generators], device=mu.device)
    alive = going.unsqueeze(1).expand(P, breadth).clone()
    steps: list[tuple[torch.Tensor, ...]] = []  # each step's (P, breadth, ...) values
    kept: list[torch.Tensor] = []  # which rollouts were alive at each step
    for _ in range(depth):
        flags = going.tolist()  # one read of the device per depth step
        drawing = [g if flags[i] else None for i, g in enumerate(generators)]
        action = controller.act(z, eps, drawing)
        next_z = model.mode(z, action) if draw == "mode" else model.sample(z, action, drawing)
        done = model.is_terminal(next_z)
        steps.append((z, action, next_z, model.predict_reward(next_z), done.float()))
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
