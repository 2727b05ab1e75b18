"""Which label-free signal tells M's wrong imagined transitions from its right ones?

For each agent run given, the transitions imagination hands C (as ``imagine evaluate`` makes
them: 100 real start observations, the agent's I_B x I_D rollouts, M's mode), judged by V's
latent classifier (which the agent never uses). For each signal, its AUROC as a detector of
the wrong ones (1: every wrong one above every right one; 0.5: chance):

- disagreement: the members' mean pairwise distance between modes (K > 1; issue 15's gate);
- support: the distance from the transition's (z, a) to the nearest real transition of the
  agent's own M_R with the same action (how far M extrapolates from its data);
- ambiguity: 1 - the weight of M's heaviest component at (z, a) (first member).

    .venv/bin/python scripts/uncertainty_check.py runs/study15/s22/hard-0 runs/study15/s24/hard-0
"""

from __future__ import annotations

import argparse

import torch

from imagine.checkpoint import load_tensors
from imagine.envs.gesture_puzzle.evaluation import auroc, imagined_transitions
from imagine.learning.agent import load_agent
from imagine.learning.gate import support_distance


@torch.no_grad()
def check(run: str, starts: int = 100, seed: int = 0) -> dict[str, float]:
    agent = load_agent(run)
    c = agent.config
    tensors = load_tensors(f"{run}/agent.safetensors", "agent checkpoint")
    held = int(tensors["real._counters"][1])  # (position, size, added)
    memory_mu = tensors["real.mu"][:held]
    memory_action = tensors["real.action"][: len(memory_mu)]
    memory_next = tensors["real.next_mu"][: len(memory_mu)]
    r, _, right = imagined_transitions(agent, starts, torch.Generator().manual_seed(seed),
                                       draw="mode")  # fmt: skip
    wrong = ~right
    mdn = agent.model.mdn if hasattr(agent.model, "mdn") else agent.model
    mixture = mdn(r["z"], r["action"])
    out = {
        "episode": agent.episode,
        "transitions": len(wrong),
        "wrong": float(wrong.mean()),
        "support": auroc(
            support_distance(r["z"], r["action"], memory_mu, memory_action).numpy(), wrong
        ),
        "support_next": auroc(torch.cdist(r["next_z"], memory_next).min(-1).values.numpy(), wrong),
        "ambiguity": auroc((1 - mixture.log_pi.exp().max(-1).values).numpy(), wrong),
    }
    if c.model_ensemble > 1:
        out["disagreement"] = auroc(r["disagreement"].numpy(), wrong)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        result = check(run)
        print(run, ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                             for k, v in result.items()))  # fmt: skip


if __name__ == "__main__":
    main()
