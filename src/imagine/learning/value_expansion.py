"""Model-based value expansion (Feinberg et al. 2018, MVE): C's target for a real transition
looks H steps further through M instead of bootstrapping at once (issue 16).

For a real transition (z, a, r, z', d) the paper's target (equation 1) is
y = r + gamma (1 - d) max_a' Q(z', a'). With horizon H, M continues from z' with C's greedy
actions: z_1 = z', and for h = 1..H, a_h = argmax_a Q(z_h, a), z_{h+1} = M's most likely next
state, r_h = r(z_{h+1}), d_h = d(z_{h+1}); then

    V_{H+1} = max_a Q'(z_{H+1}, a)
    V_h     = r_h + gamma (1 - d_h) V_{h+1}        (h = H..1)
    y       = r + gamma (1 - d) V_1,

so H = 0 is equation 1. The imagined steps use M without dropout and Q' is what the
controller bootstraps with (its target network or double-DQN reading when those are on).
Storing imagined transitions (Algorithm 1) and expanding targets are two uses of the same M;
``value_expansion`` turns the second on beside the first.
"""

from __future__ import annotations

import torch

from imagine.models.controller import PopulationController
from imagine.models.world_model import PopulationWorldModel


@torch.no_grad()
def expanded_target(
    controller: PopulationController,
    model: PopulationWorldModel,
    reward: torch.Tensor,
    next_z: torch.Tensor,
    done: torch.Tensor,
    horizon: int,
) -> torch.Tensor:
    """The H-step target y (P, B) for real transitions with rewards and ends (P, B) and next
    latents (P, B, D), as the module describes."""
    z = next_z
    steps: list[tuple[torch.Tensor, torch.Tensor]] = []
    for _ in range(horizon):
        action = controller.q(z).argmax(-1)
        z = model.mode(z, action)
        steps.append((model.predict_reward(z), model.is_terminal(z).float()))
    value = controller.bootstrap_value(z)
    for r, d in reversed(steps):
        value = r + controller.gamma * (1.0 - d) * value
    return reward + controller.gamma * (1.0 - done) * value
