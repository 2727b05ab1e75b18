"""Model-based value expansion (Feinberg et al. 2018, MVE): C's target for a real transition
looks H steps further through M instead of bootstrapping at once (issue 16).

For a real transition (z, a, r, z', d) the paper's target (equation 1) is
y = r + gamma (1 - d) max_a' Q(z', a'). With horizon H, M continues from z' with C's greedy
actions: z_1 = z', and for h = 1..H, a_h = argmax_a Q(z_h, a), z_{h+1} = M's most likely next
state (with an ensemble, K >= 2, its first member's, or with ``value_expansion_members:
mean`` the members' mean mode (1 / K) sum_k mode_k, the point prediction that
:meth:`WorldModel.most_likely` gives the accuracy and generalization checks), r_h = r(z_{h+1}),
d_h = d(z_{h+1}); then

    V_{H+1} = max_a Q'(z_{H+1}, a)
    V_h     = r_h + gamma (1 - d_h) V_{h+1}        (h = H..1)
    y       = r + gamma (1 - d) V_1,

so H = 0 is equation 1. The imagined steps use M without dropout and Q' is what the
controller bootstraps with (its target network or double-DQN reading when those are on).
Storing imagined transitions (Algorithm 1) and expanding targets are two uses of the same M;
``value_expansion`` turns the second on beside the first.

With an ensemble of K MDNs (``model_ensemble`` >= 2), ``value_expansion_weighting: steve``
mixes the horizons instead of taking the last (STEVE, Buckman et al. 2018). Each member k
rolls out on its own from z' (its own most likely states, C's greedy actions on them), which
gives every horizon j = 0..H a candidate inner value per member,

    W_j^k = sum_{i=1..j} c_{i-1}^k r_i^k + c_j^k Q'(z_{j+1}^k),   c_0 = 1,
    c_i^k = c_{i-1}^k gamma (1 - d_i^k),

(W_0 = Q'(z'), equation 1's), and the target is y = r + gamma (1 - d) sum_j w_j mean_k W_j^k
with inverse-variance weights w_j proportional to 1 / sigma_j^2. STEVE takes sigma_j^2 over
ensembles of M, r and Q; here only M is an ensemble, so sigma_j^2 is the members' variance of
W_j^k (over the K members, dividing by K as STEVE does) plus the bootstrap's share,
(mean_k c_j^k)^2 sigma_Q^2, with sigma_Q^2 Q's error variance estimated, per agent and
without labels, by the batch's mean squared TD error under equation 1. Where the members
agree, longer horizons weigh more (their bootstrap is discounted by gamma^j); where they
part, the weight returns to the short horizons and, at the limit, to equation 1.
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
    members: str = "first",
) -> torch.Tensor:
    """The H-step target y (P, B) for real transitions with rewards and ends (P, B) and next
    latents (P, B, D), as the module describes; ``members``: an ensemble's first member's
    modes or their ``mean``."""
    z = next_z
    steps: list[tuple[torch.Tensor, torch.Tensor]] = []
    for _ in range(horizon):
        action = controller.q(z).argmax(-1)
        if members == "mean" and model.ensemble > 1:
            z = model.mean_mode(z, action)
        else:
            z = model.mode(z, action)
        steps.append((model.predict_reward(z), model.is_terminal(z).float()))
    value = controller.bootstrap_value(z)
    for r, d in reversed(steps):
        value = r + controller.gamma * (1.0 - d) * value
    return reward + controller.gamma * (1.0 - done) * value


@torch.no_grad()
def steve_target(
    controller: PopulationController,
    model: PopulationWorldModel,
    z: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    next_z: torch.Tensor,
    done: torch.Tensor,
    horizon: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """STEVE's target y (P, B) for real transitions (z, a, r, z', d) (P, B, ...) through the
    members of an ensemble M, as the module describes; with each agent's mean horizon
    sum_j j w_j over the batch's transitions that did not end (P,; 0 where all ended)."""
    values, continuations = member_values(controller, model, next_z, horizon)
    q = controller.q(z).gather(-1, action.unsqueeze(-1)).squeeze(-1)
    q_variance = (controller.td_target(reward, next_z, done) - q).square().mean(-1)  # (P,)
    members = values.var(2, correction=0)  # over the K members, as STEVE's moments
    variance = members + continuations.mean(2).square() * q_variance[None, :, None]
    weights = 1.0 / (variance + 1e-8)  # (H + 1, P, B)
    weights = weights / weights.sum(0, keepdim=True)
    inner = (weights * values.mean(2)).sum(0)
    steps = torch.arange(horizon + 1, dtype=weights.dtype, device=weights.device)
    going = 1.0 - done  # where the real transition ended, the rollout does not count
    per_row = (weights * steps[:, None, None]).sum(0)
    mean_horizon = (per_row * going).sum(-1) / going.sum(-1).clamp(min=1.0)
    return reward + controller.gamma * (1.0 - done) * inner, mean_horizon


@torch.no_grad()
def member_values(
    controller: PopulationController, model: PopulationWorldModel, next_z: torch.Tensor,
    horizon: int,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Each member's candidate inner values W_j^k and continuations c_j^k, (H + 1, P, K, B),
    from next latents (P, B, D): member k rolls out alone (:meth:`PopulationWorldModel.
    member_paths`)."""
    P, B, D = next_z.shape
    K = model.ensemble
    state = next_z.unsqueeze(1).expand(P, K, B, D)

    def flat(x: torch.Tensor) -> torch.Tensor:  # (P, K, B, ...) -> (P, K * B, ...)
        return x.reshape(P, K * B, *x.shape[3:])

    def unflat(x: torch.Tensor) -> torch.Tensor:  # (P, K * B) -> (P, K, B)
        return x.reshape(P, K, B)

    partial = next_z.new_zeros(P, K, B)  # sum_{i <= j} c_{i-1} r_i
    discount = next_z.new_ones(P, K, B)  # c_j
    values, continuations = [], []
    for j in range(horizon + 1):
        values.append(partial + discount * unflat(controller.bootstrap_value(flat(state))))
        continuations.append(discount)
        if j == horizon:
            break
        action = unflat(controller.q(flat(state)).argmax(-1))
        state = model.member_paths(state, action)
        partial = partial + discount * unflat(model.predict_reward(flat(state)))
        ended = unflat(model.is_terminal(flat(state)).float())
        discount = discount * controller.gamma * (1.0 - ended)
    return torch.stack(values), torch.stack(continuations)
