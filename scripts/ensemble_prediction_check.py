"""How should an ensemble of Ms name one next state? Each way against the first member alone.

For each agent run given (K > 1), over all 192 x 6 (state, action) pairs, from each
macrostate's reference latent and from one rendered observation of it: how often V's
classifier reads the right next macrostate from the first member's mode, from each member's
(their mean accuracy), from the mean of the members' modes (``WorldModel.most_likely``), from
a majority vote of the members' reads, and from the mode of the members' pooled mixture
(the component mean of highest density under (1 / K) sum_k p_k). Split into transitions from
terminal states (M never trains on them: generalization) and the rest.

    .venv/bin/python scripts/ensemble_prediction_check.py runs/study20/s93/hard-{0,1,2,3,4}
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import torch

from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.rules import N_ACTIONS, all_macrostates, apply_actions, is_terminal
from imagine.learning.agent import load_agent
from imagine.models.world_model import component_log_normal


def pooled_mode(members, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """The candidate (any member's component mean) of highest density under the members'
    equally weighted pooled mixture."""
    mixtures = [mdn(z, a) for mdn in members]
    candidates = torch.cat([m.mu for m in mixtures], 1)  # (N, K * C, D)
    log_density = torch.stack([
        torch.stack([torch.logsumexp(m.log_pi + component_log_normal(m, candidates[:, j]), -1)
                     for j in range(candidates.shape[1])], 1)
        for m in mixtures
    ]).logsumexp(0)  # fmt: skip
    return candidates[torch.arange(len(candidates)), log_density.argmax(-1)]


@torch.no_grad()
def check(run: str) -> dict[str, float]:
    agent = load_agent(run)
    model, encoder = agent.model.eval(), agent.encoder
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    truth = apply_actions(states, actions)
    terminal = is_terminal(states, agent.config.task)
    images = make_composer().sample(np.random.default_rng(0), states)
    a = torch.as_tensor(actions)
    out = {}
    for source in ("reference", "observed"):
        if source == "reference":
            z = encoder.state_latents().repeat_interleave(N_ACTIONS, dim=0)
        else:
            z, _ = encoder.encode(images, states)
        modes = torch.stack([mdn.most_likely(z, a) for mdn in model.members])
        reads = np.stack([encoder.classify(m).numpy() for m in modes])  # (K, N, 4)
        votes = np.array([Counter(map(tuple, reads[:, i])).most_common(1)[0][0]
                          for i in range(len(states))])  # fmt: skip
        pooled = encoder.classify(pooled_mode(model.members, z, a)).numpy()
        right = {
            "first member": (reads[0] == truth).all(-1),
            "each member": (reads == truth).all(-1).mean(0),
            "mean mode": (encoder.classify(model.most_likely(z, a)).numpy() == truth).all(-1),
            "vote": (votes == truth).all(-1),
            "pooled mode": (pooled == truth).all(-1),
        }
        for part, rows in (("terminal", terminal), ("nonterminal", ~terminal)):
            for way, r in right.items():
                out[f"{source} {part}, {way}"] = float(r[rows].mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = []
    for run in args.runs:
        results.append(check(run))
        print(run, ", ".join(f"{k} {100 * v:.1f}" for k, v in results[-1].items()), flush=True)
    print("mean (std) over the runs:")
    for key in results[0]:
        x = 100 * np.array([r[key] for r in results])
        print(f"  {key}: {x.mean():.1f} ({x.std(ddof=1) if len(x) > 1 else 0.0:.1f})")


if __name__ == "__main__":
    main()
