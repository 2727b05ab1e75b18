"""Can M's own features carry draws that are right? Refit M's mixture heads, body frozen.

A perfect M of the paper's form (5 diagonal components per transition) could draw the right
macrostate about 97% of the time with the fast V (`scripts/m_sample_bound.py`: a 5-component
diagonal mixture fitted to each macrostate's cloud), while the agents' M draws right on about
65%. This script asks whether what M has learned already holds the rest: for each run given
(an augmented agent's last checkpoint), it takes M's first member, freezes its body in eval
mode (no dropout masks: the network that predicts), and fits copies of its three heads
(``--fresh``: newly initialized ones)
(weights, means, scales) by equation (5) on the agent's real memory M_R, with the start
latents drawn from V's N(mu, sigma) as M learns, and the targets either drawn too (as the
`fast` M learns) or V's means. Prints, as `imagine evaluate`'s `transition_sampled` judges
draws (from each macrostate's reference latent over the task's non-terminal transitions,
read back by V's classifier; here the mean over ``--draws`` draws), the draws right, the
mode right, and the mean weight of the heaviest component, for M's own heads and the refits.

    .venv/bin/python scripts/m_draw_heads.py runs/study23/s93/hard-{0,1,2,3,4} [--updates 4000]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from imagine.envs.gesture_puzzle.rules import N_ACTIONS, all_macrostates, apply_actions, is_terminal
from imagine.learning.agent import load_agent
from imagine.models.world_model import (
    MDN,
    Mixture,
    mixture_from_heads,
    mixture_mode,
    mixture_nll,
    sample_mixture,
)

sys.path.insert(0, str(Path(__file__).parent))
from m_offline import real_memory

Heads = tuple[torch.nn.Linear, torch.nn.Linear, torch.nn.Linear]


def mixture(mdn: MDN, heads: Heads, z: torch.Tensor, action: torch.Tensor) -> Mixture:
    """The mixture of ``heads`` on the frozen body's features (no dropout), residual as M."""
    with torch.no_grad():
        h = mdn.body(torch.cat([z, F.one_hot(action, mdn.n_actions).to(z)], dim=-1))
    return mixture_from_heads(*(head(h) for head in heads), mdn.latent_dim, mdn.min_sigma,
                              z if mdn.residual else None)  # fmt: skip


@torch.no_grad()
def judge(agent, mdn: MDN, heads: Heads, draws: int) -> tuple[float, float, float]:
    """(draws right, mode right, mean heaviest weight) over the non-terminal transitions."""
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    seen = ~is_terminal(states, agent.config.task)
    truth = apply_actions(states, actions)[seen]
    z = agent.encoder.state_latents().repeat_interleave(N_ACTIONS, 0)[seen]
    m = mixture(mdn, heads, z, torch.as_tensor(actions[seen]))
    generator = torch.Generator().manual_seed(0)
    right = [(agent.encoder.classify(sample_mixture(m, generator)).numpy() == truth).all(-1)
             for _ in range(draws)]  # fmt: skip
    mode = (agent.encoder.classify(mixture_mode(m)).numpy() == truth).all(-1)
    return float(np.mean(right)), float(mode.mean()), float(m.log_pi.exp().max(-1).values.mean())


def refit(mdn: MDN, memory, updates: int, batch: int, targets: str, fresh: bool) -> Heads:
    """Copies of M's heads (``fresh``: new heads of their shapes, PyTorch's initialization)
    fitted by equation (5) on M_R, the body frozen."""
    torch.manual_seed(0)
    own = (mdn.pi_head, mdn.mu_head, mdn.sigma_head)
    heads = tuple((torch.nn.Linear(h.in_features, h.out_features) if fresh else copy.deepcopy(h))
                  .requires_grad_(True) for h in own)  # fmt: skip
    optimizer = torch.optim.Adam([p for h in heads for p in h.parameters()], lr=1e-3)
    generator = torch.Generator().manual_seed(0)
    for _ in range(updates):
        b = {k: v[0] for k, v in memory.sample(batch, [generator]).items()}
        z = b["mu"] + b["sigma"] * torch.randn(b["mu"].shape, generator=generator)
        target = b["next_mu"]
        if targets == "draws":
            target = target + b["next_sigma"] * torch.randn(target.shape, generator=generator)
        loss = mixture_nll(mixture(mdn, heads, z, b["action"]), target).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return heads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--updates", type=int, default=4000)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--draws", type=int, default=20, help="draws per transition")
    parser.add_argument("--fresh", action="store_true", help="refit new heads, not M's copies")
    args = parser.parse_args()
    torch.set_num_threads(1)
    found: dict[str, list[tuple[float, float, float]]] = {}
    for run in args.runs:
        agent = load_agent(run)
        mdn = agent.model.mdn.eval().requires_grad_(False)
        memory = real_memory(run, agent.encoder.latent_dim)
        rows = {"M's own heads": judge(agent, mdn, (mdn.pi_head, mdn.mu_head, mdn.sigma_head),
                                       args.draws)}  # fmt: skip
        for targets in ("draws", "means"):
            heads = refit(mdn, memory, args.updates, args.batch, targets, args.fresh)
            rows[f"heads refit, targets V's {targets}"] = judge(agent, mdn, heads, args.draws)
        cells = [f"{k} {d:.1%} / {m:.1%} / {w:.2f}" for k, (d, m, w) in rows.items()]
        print(f"{run} ({len(memory)} real transitions): " + "; ".join(cells), flush=True)
        for key, value in rows.items():
            found.setdefault(key, []).append(value)
    head = f"M's first member, {len(args.runs)} runs"
    print(f"\n| {head} | draws right | mode right | heaviest weight |")
    print("| --- | --- | --- | --- |")
    for key, values in found.items():
        x = 100 * np.array(values)
        spread = x[:, 0].std(ddof=1) if len(x) > 1 else 0.0
        print(f"| {key} | {x[:, 0].mean():.1f} ({spread:.1f}) | {x[:, 1].mean():.1f} | "
              f"{x[:, 2].mean() / 100:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
