"""Do M's draws become right when projected back onto V's manifold (issue 14's candidate)?

Each of M's draws (and its most likely next state) is replaced by the nearest real next
latent the agent holds in M_R (V's mean of an image it saw; Euclidean distance in V's latent
space), so that imagination hands C only points V has produced. Judged as `imagine
evaluate` judges M (from each macrostate's reference latent, read back by V's classifier,
which the agent never uses): draws over the task's non-terminal transitions (``--draws`` per
transition), the mode over the same and over the transitions from terminal states
(generalization), each raw and snapped; and how many of the true next states appear in M_R
at all. Last, V's spacing: the distance from each macrostate's reference latent to the
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

sys.path.insert(0, str(Path(__file__).parent))
from m_offline import real_memory


def snap(points: torch.Tensor, bank: torch.Tensor) -> torch.Tensor:
    """Each row of ``points`` replaced by its nearest row of ``bank`` (Euclidean)."""
    return bank[torch.cdist(points, bank).argmin(-1)]


@torch.no_grad()
def check(run: Path, draws: int) -> dict[str, float]:
    agent = load_agent(run)
    encoder, model = agent.encoder, agent.model.eval()
    bank = real_memory(run, encoder.latent_dim).state_dict("real")["real.next_mu"]
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
    mode = model.most_likely(z, action)
    everywhere = np.ones(len(truth), bool)
    mode_raw, mode_snapped = right(mode, everywhere), right(snap(mode, bank), everywhere)
    banked = {tuple(row) for row in encoder.classify(bank).numpy().tolist()}
    in_bank = np.array([tuple(row) in banked for row in truth.tolist()])
    return {
        "draws right": float(np.mean(raw)),
        "draws right, snapped": float(np.mean(snapped)),
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
        print(f"| {key} | {100 * x.mean():.1f} ({100 * x.std(ddof=1) if len(x) > 1 else 0:.1f}) |")
    spacing = nearest_other(load_agent(args.runs[0]).encoder.state_latents())
    print(
        f"\nV's reference latents, distance to the nearest other macrostate's: min "
        f"{spacing.min():.2f}, median {spacing.median():.2f}, max {spacing.max():.2f}"
    )


if __name__ == "__main__":
    main()
