"""Which label-free signal tells M's wrong imagined transitions from its right ones?

For each agent run given, the transitions imagination hands C (as ``imagine evaluate`` makes
them: 100 real start observations, the agent's I_B x I_D rollouts, M's mode), judged by V's
latent classifier (which the agent never uses). For each signal, its AUROC as a detector of
the wrong ones (1: every wrong one above every right one; 0.5: chance):

- disagreement: the members' mean pairwise distance between modes (K > 1; issue 15's gate);
- support: the distance from the transition's (z, a) to the nearest real transition of the
  agent's own M_R with the same action (how far M extrapolates from its data);
- ambiguity: 1 - the weight of M's heaviest component at (z, a) (first member);
- depth: the transition's step in its rollout (0 for first steps: deeper ones start from
  imagined latents);
- lookup: the distance from M's next state to what the nearest real transition with the same
  action says it is (that transition's next mu, moved by z minus its start), a second,
  non-parametric model's disagreement with M;
- cycle: how far V moves M's next state when it draws it and sees it again,
  ||z' - E(D(z'))|| with D V's decoder and E its encoder's mean: a latent off the images V
  knows (a drifted hand) comes back elsewhere. ``cycle_read``: whether V's classifier reads
  another macrostate from E(D(z')) than from z' (ties count a half).

And where the wrong ones are: their share on first steps and on later ones, and the share of
them whose arrows are right and only the hand is wrong.

    .venv/bin/python scripts/uncertainty_check.py runs/study15/s22/hard-0 runs/study15/s24/hard-0
"""

from __future__ import annotations

import argparse

import torch

from imagine.checkpoint import load_tensors
from imagine.envs.gesture_puzzle.evaluation import auroc, imagined_transitions
from imagine.learning.agent import load_agent
from imagine.learning.gate import support_distance


def nearest_start(
    r: dict[str, torch.Tensor], memory_mu: torch.Tensor, memory_action: torch.Tensor
) -> torch.Tensor:
    """Per imagined transition (z, a), the index j of the real transition with action a whose
    start mu_j is nearest z."""
    distance = torch.cdist(r["z"], memory_mu)
    distance = distance.masked_fill(r["action"].unsqueeze(1) != memory_action.unsqueeze(0), 1e9)
    return distance.argmin(-1)


def lookup_distance(
    r: dict[str, torch.Tensor],
    memory_mu: torch.Tensor,
    memory_action: torch.Tensor,
    memory_next: torch.Tensor,
) -> torch.Tensor:
    """Per imagined transition, ||z' - (next_mu_j + z - mu_j)|| for the real transition j with
    the same action whose start mu_j is nearest z."""
    j = nearest_start(r, memory_mu, memory_action)
    return (r["next_z"] - (memory_next[j] + r["z"] - memory_mu[j])).norm(dim=-1)


@torch.no_grad()
def cycled(encoder, z: torch.Tensor, batch: int = 1000) -> torch.Tensor | None:
    """E(D(z)) for latents z in the agent's space (None for an encoder without V): V's decoder
    draws each latent, V's encoder reads the drawing back (its mean)."""
    inner = getattr(encoder, "inner", encoder)
    vae = getattr(inner, "vae", None)
    if vae is None:
        return None
    full = encoder.unproject(z) if inner is not encoder else z
    back = torch.cat([vae.encode(vae.decode(part))[0] for part in full.split(batch)])
    return encoder.project(back) if inner is not encoder else back


@torch.no_grad()
def check(run: str, starts: int = 100, seed: int = 0) -> dict[str, float]:
    agent = load_agent(run)
    c = agent.config
    tensors = load_tensors(f"{run}/agent.safetensors", "agent checkpoint")
    held = int(tensors["real._counters"][1])  # (position, size, added)
    memory_mu = tensors["real.mu"][:held]
    memory_action = tensors["real.action"][: len(memory_mu)]
    memory_next = tensors["real.next_mu"][: len(memory_mu)]
    r, truth, right = imagined_transitions(agent, starts, torch.Generator().manual_seed(seed),
                                           draw="mode")  # fmt: skip
    wrong = ~right
    shown = agent.encoder.classify(r["next_z"]).numpy()
    hand_only = (shown[..., :3] == truth[..., :3]).all(-1) & (shown[..., 3] != truth[..., 3])
    first = (r["step"] == 0).numpy()
    mdn = agent.model.mdn if hasattr(agent.model, "mdn") else agent.model
    mixture = mdn(r["z"], r["action"])
    out = {
        "episode": agent.episode,
        "transitions": len(wrong),
        "wrong": float(wrong.mean()),
        "wrong_first_step": float(wrong[first].mean()),
        "wrong_later_steps": float(wrong[~first].mean()) if (~first).any() else float("nan"),
        "wrong_hand_only": float(hand_only[wrong].mean()) if wrong.any() else float("nan"),
        "support": auroc(
            support_distance(r["z"], r["action"], memory_mu, memory_action).numpy(), wrong
        ),
        "support_next": auroc(torch.cdist(r["next_z"], memory_next).min(-1).values.numpy(), wrong),
        "ambiguity": auroc((1 - mixture.log_pi.exp().max(-1).values).numpy(), wrong),
        "depth": auroc(r["step"].float().numpy(), wrong),
        "lookup": auroc(lookup_distance(r, memory_mu, memory_action, memory_next).numpy(), wrong),
    }
    back = cycled(agent.encoder, r["next_z"])
    if back is not None:
        out["cycle"] = auroc((r["next_z"] - back).norm(dim=-1).numpy(), wrong)
        read_back = agent.encoder.classify(back).numpy()
        out["cycle_read"] = auroc((read_back != shown).any(-1).astype(float), wrong)
        out["cycle_wrong"] = float(1 - (read_back == truth).all(-1).mean())
    if c.model_ensemble > 1:
        out["disagreement"] = auroc(r["disagreement"].numpy(), wrong)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--starts", type=int, default=100, help="real start states per agent")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        result = check(run, args.starts)
        print(run, ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                             for k, v in result.items()))  # fmt: skip


if __name__ == "__main__":
    main()
