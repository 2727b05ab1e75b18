"""Imagined rollouts: M run in closed loop like an environment (paper section IV; Algorithm 1,
lines 17-18).

``I_B`` rollouts start from the current real latent state (each a sample of V's N(mu, sigma)),
act with C epsilon-greedily, draw the next state from the MDN and feed it back, take the reward
from the r-network and end a rollout where the d-network says terminal, after at most ``I_D``
steps. M runs in evaluation mode (no dropout) while it imagines.
"""

from __future__ import annotations

import torch

from imagine.controller import Controller
from imagine.world_model import WorldModel


@torch.no_grad()
def imagine_rollouts(
    model: WorldModel,
    controller: Controller,
    mu: torch.Tensor,
    sigma: torch.Tensor,
    breadth: int,
    depth: int,
    eps: float,
    generator: torch.Generator,
) -> dict[str, torch.Tensor]:
    """Transitions ``(z, action, next_z, reward, done)`` of ``breadth`` rollouts of up to
    ``depth`` steps from the latent posterior ``N(mu, sigma)`` (each (latent_dim,))."""
    was_training = model.training
    model.eval()
    noise = torch.randn((breadth, mu.shape[-1]), generator=generator, device=mu.device)
    z = mu + sigma * noise
    alive = torch.ones(breadth, dtype=torch.bool, device=mu.device)
    out: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("z", "action", "next_z", "reward", "done")
    }
    for _ in range(depth):
        action = controller.act(z, eps, generator)
        next_z = model.mdn.sample(z, action, generator)
        reward = model.reward(next_z)
        done = model.terminal.is_terminal(next_z)
        for key, value in zip(out, (z, action, next_z, reward, done.float()), strict=True):
            out[key].append(value[alive])
        alive &= ~done
        if not alive.any():
            break
        z = next_z
    model.train(was_training)
    return {key: torch.cat(values) for key, values in out.items()}
