"""What M's r- and d-networks know early (issue 14, round 6): for a trained agent, r and d at
every macrostate's mean latent by kind (goal, illegal, step), how its imagined transitions'
rewards compare with the rules', and fresh r and d trained offline on its M_R (the paper's
log-cosh or MSE, on V's samples or means) for 1000 and 4000 updates of 128.

    .venv/bin/python scripts/reward_check.py runs/e400/seed-0 runs/e400/seed-1
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
import torch.nn.functional as F

from imagine.checkpoint import load_tensors
from imagine.envs.gesture_puzzle.evaluation import imagined_transitions
from imagine.envs.gesture_puzzle.rules import REWARD_GOAL, all_macrostates, is_terminal, rewards
from imagine.learning.agent import load_agent
from imagine.models.world_model import RewardNet, TerminalNet, log_cosh


def by_kind(r: torch.Tensor, d: torch.Tensor, task: str) -> str:
    """r's mean and mean error and d's error rate over the goal, illegal and step states."""
    states = all_macrostates()
    true_r = torch.tensor(rewards(states, task), dtype=torch.float32)
    true_d = torch.as_tensor(is_terminal(states, task))
    kinds = {"goal": true_r == REWARD_GOAL, "illegal": true_r == -5.0, "step": true_r == -1.0}
    out = []
    for name, m in kinds.items():
        error = (r[m] - true_r[m]).abs().mean()
        wrong = (d[m] != true_d[m]).float().mean()
        out.append(f"{name} ({int(m.sum())}): r {r[m].mean():6.2f}, |error| {error:5.2f}, "
                   f"d wrong {wrong:.2f}")  # fmt: skip
    return " | ".join(out)


def offline(tensors, latents, task, loss: str, resample: bool, updates: int) -> str:
    """Fresh r and d (the fast preset's sizes) trained on the agent's M_R alone."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    next_mu, next_sigma = tensors["real.next_mu"], tensors["real.next_sigma"]
    reward, done = tensors["real.reward"], tensors["real.done"]
    r, d = RewardNet(8, hidden=128, dropout=0.0), TerminalNet(8, dropout=0.0)
    optimizer = torch.optim.Adam([*r.parameters(), *d.parameters()], lr=1e-3)
    for _ in range(updates):
        i = torch.randint(len(reward), (128,), generator=g)
        z = next_mu[i]
        if resample:
            z = z + next_sigma[i] * torch.randn(z.shape, generator=g)
        error = r(z) - reward[i]
        loss_r = log_cosh(error).mean() if loss == "logcosh" else 0.5 * error.square().mean()
        loss_d = F.binary_cross_entropy_with_logits(d(z), done[i])
        optimizer.zero_grad()
        (loss_r + loss_d).backward()
        optimizer.step()
    with torch.no_grad():
        return by_kind(r(latents), d(latents) > 0, task)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="agent run folders")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        agent = load_agent(run)
        task, latents = agent.config.task, agent.encoder.state_latents()
        with torch.no_grad():
            r, d = agent.model.reward(latents), agent.model.terminal(latents) > 0
        tensors = load_tensors(f"{run}/agent.safetensors", "agent checkpoint")
        goals = int((tensors["real.reward"] == REWARD_GOAL).sum())
        print(f"{run}: M_R {len(tensors['real.reward'])} transitions, {goals} into a goal")
        print("  its r and d:", by_kind(r, d, task))
        rollout, truth, _ = imagined_transitions(agent, 300, torch.Generator().manual_seed(0))
        true_r, imagined_r = rewards(truth, task), rollout["reward"].numpy()
        print(
            f"  imagined: {len(true_r)} transitions, {np.mean(true_r == REWARD_GOAL):.1%} truly "
            f"into a goal, r > 25 on {np.mean(imagined_r > REWARD_GOAL / 2):.1%}, mean |r error| "
            f"{np.abs(imagined_r - true_r).mean():.2f}"
        )
        for loss in ("logcosh", "mse"):
            for resample in (True, False):
                for updates in (1000, 4000):
                    latent = "samples" if resample else "means"
                    print(f"  offline {loss}, {latent}, {updates} updates:",
                          offline(tensors, latents, task, loss, resample, updates))  # fmt: skip


if __name__ == "__main__":
    main()
