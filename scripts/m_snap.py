"""Do M's draws become right when projected back onto V's manifold (issue 14's candidate)?

Each of M's draws (and its most likely next state) is replaced by the nearest real next
latent the agent holds in M_R (V's mean of an image it saw; Euclidean distance in V's latent
space), so that imagination hands C only points V has produced. Judged as `imagine
evaluate` judges M (from each macrostate's reference latent, read back by V's classifier,
which the agent never uses): draws over the task's non-terminal transitions (``--draws`` per
transition), the mode over the same and over the transitions from terminal states
(generalization), each raw and snapped; and how many of the true next states appear in M_R
at all. Besides the nearest point, a softer projection: each draw *resampled* from M_R's next
latents, point j with probability proportional to M's mixture density at it (M's distribution
restricted to the points V produced: a draw from the product of M's mixture and M_R's
empirical distribution of next latents), and the median effective number of points it draws
among. And a *lookup* model for comparison, M_R itself: the next latent of the real transition
with the same action whose start is nearest (`scripts/uncertainty_check.py`).
Last, V's spacing: the distance from each macrostate's reference latent to the
nearest other macrostate's (the first run's V).

    .venv/bin/python scripts/m_snap.py runs/study23/s93/hard-{0,1,2,3,4} [--draws 20]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from imagine.envs.gesture_puzzle.rules import N_ACTIONS, all_macrostates, apply_actions, is_terminal
from imagine.learning.agent import load_agent
from imagine.models.world_model import Mixture, mixture_nll

sys.path.insert(0, str(Path(__file__).parent))
from m_offline import real_memory
from uncertainty_check import nearest_start


def snap(points: torch.Tensor, bank: torch.Tensor) -> torch.Tensor:
    """Each row of ``points`` replaced by its nearest row of ``bank`` (Euclidean)."""
    return bank[torch.cdist(points, bank).argmin(-1)]


def bank_log_density(m: Mixture, bank: torch.Tensor, chunk: int = 1024) -> torch.Tensor:
    """log p_M(bank_j) of each row's mixture (N rows) at every bank point (J, D): (N, J)."""
    rows = Mixture(m.log_pi[:, None], m.mu[:, None], m.sigma[:, None],
                   None if m.tril is None else m.tril[:, None])  # fmt: skip
    return torch.cat([-mixture_nll(rows, bank[j : j + chunk]) for j in range(0, len(bank), chunk)],
                     dim=1)  # fmt: skip


def resample(m: Mixture, bank: torch.Tensor, generator: torch.Generator, draws: int = 1):
    """``draws`` bank points per row (draws, N, D), each drawn with probability proportional
    to the row's mixture density there; with the effective number of points each row draws
    among, 1 / sum w^2 (N,)."""
    weights = bank_log_density(m, bank).softmax(-1)
    index = torch.multinomial(weights, draws, replacement=True, generator=generator)
    return bank[index.T], 1.0 / weights.square().sum(-1)


@torch.no_grad()
def check(run: Path, draws: int) -> dict[str, float]:
    agent = load_agent(run)
    encoder, model = agent.encoder, agent.model.eval()
    held = real_memory(run, encoder.latent_dim).state_dict("real")
    bank = held["real.next_mu"]
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    truth = apply_actions(states, actions)
    z = encoder.state_latents().repeat_interleave(N_ACTIONS, 0)
    action = torch.as_tensor(actions)
    seen = ~is_terminal(states, agent.config.task)

    def right(latents: torch.Tensor, rows: np.ndarray) -> np.ndarray:
        return (encoder.classify(latents).numpy() == truth[rows]).all(-1)

    generator = torch.Generator().manual_seed(0)
    raw, snapped = [], []
    for _ in range(draws):
        sample = model.mdn.sample(z[seen], action[seen], generator)
        raw.append(right(sample, seen))
        snapped.append(right(snap(sample, bank), seen))
    resampled, effective = resample(model.mdn(z[seen], action[seen]), bank, generator, draws)
    resampled_right = [right(points, seen) for points in resampled]
    looked_up = nearest_start({"z": z[seen], "action": action[seen]}, held["real.mu"],
                              held["real.action"])  # fmt: skip
    mode = model.most_likely(z, action)
    everywhere = np.ones(len(truth), bool)
    mode_raw, mode_snapped = right(mode, everywhere), right(snap(mode, bank), everywhere)
    banked = {tuple(row) for row in encoder.classify(bank).numpy().tolist()}
    in_bank = np.array([tuple(row) in banked for row in truth.tolist()])
    return {
        "draws right": float(np.mean(raw)),
        "draws right, snapped": float(np.mean(snapped)),
        "draws resampled from M_R": float(np.mean(resampled_right)),
        "points a resampled draw draws among (median)": float(effective.median()),
        "lookup (M_R's nearest start, same action)": float(right(bank[looked_up], seen).mean()),
        "mode right": float(mode_raw[seen].mean()),
        "mode right, snapped": float(mode_snapped[seen].mean()),
        "from terminal states": float(mode_raw[~seen].mean()),
        "from terminal states, snapped": float(mode_snapped[~seen].mean()),
        "true next state in M_R (non-terminal)": float(in_bank[seen].mean()),
        "true next state in M_R (from terminal)": float(in_bank[~seen].mean()),
    }


def nearest_other(latents: torch.Tensor) -> torch.Tensor:
    """Per row, the distance to the nearest other row."""
    distance = torch.cdist(latents, latents)
    return distance.fill_diagonal_(float("inf")).min(-1).values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--draws", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for run in args.runs:
        rows.append(check(run, args.draws))
        print(run, ", ".join(f"{k} {v:.3f}" for k, v in rows[-1].items()), flush=True)
    print(f"\n| over {len(rows)} runs | mean (std) |\n| --- | --- |")
    for key in rows[0]:
        x = np.array([row[key] for row in rows])
        scale = 1 if key.startswith("points") else 100
        spread = scale * x.std(ddof=1) if len(x) > 1 else 0
        print(f"| {key} | {scale * x.mean():.1f} ({spread:.1f}) |")
    spacing = nearest_other(load_agent(args.runs[0]).encoder.state_latents())
    print(
        f"\nV's reference latents, distance to the nearest other macrostate's: min "
        f"{spacing.min():.2f}, median {spacing.median():.2f}, max {spacing.max():.2f}"
    )


if __name__ == "__main__":
    main()
