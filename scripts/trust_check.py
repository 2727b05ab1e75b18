"""Would M be trusted? Two one-step rules on fresh real transitions, against the truth.

For each agent run given: 2000 transitions from random non-terminal macrostates and actions,
each observed as fresh images (new fragments) through the agent's encoder. Prints how often
M's most likely next state names the right macrostate (V's latent classifier, which the agent
never uses), and the share each trust rule passes:

- radius: the mode lands within 3 of V's posterior sigmas of the observed next latent (the
  first rule of ``imagine.learning.gate``);
- action: the mode for the action taken is the nearest of all actions' modes to the observed
  next latent (the rule now in ``imagine.learning.gate``; a tie of n counts 1/n).

    .venv/bin/python scripts/trust_check.py runs/study14/s18/hard-0 runs/study14/s19/hard-0
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.rules import N_ACTIONS, all_macrostates, apply_actions, is_terminal
from imagine.learning.agent import load_agent
from imagine.learning.imagination import posterior_scale

RADIUS = 3.0


@torch.no_grad()
def check(run: str, n: int = 2000) -> dict[str, float]:
    agent = load_agent(run)
    rng = np.random.default_rng(0)
    states = all_macrostates()
    states = states[~is_terminal(states, agent.config.task)]
    states = states[rng.integers(len(states), size=n)]
    actions = rng.integers(N_ACTIONS, size=n)
    truth = apply_actions(states, actions)
    composer = make_composer()
    mu, sigma = agent.encoder.encode(composer.sample(rng, states), states)
    next_mu, _ = agent.encoder.encode(composer.sample(rng, truth), truth)
    modes = torch.stack(
        [agent.model.mdn.most_likely(mu, torch.full((n,), a)) for a in range(N_ACTIONS)], 1
    )  # (n, A, D)
    miss = (modes - next_mu[:, None]).norm(dim=-1)  # (n, A)
    taken = miss[torch.arange(n), torch.as_tensor(actions)]
    nearest = miss <= miss.min(-1, keepdim=True).values + 1e-6
    action_rule = nearest[torch.arange(n), torch.as_tensor(actions)] / nearest.sum(-1)
    right = torch.as_tensor((agent.encoder.classify(modes[torch.arange(n), actions]).numpy()
                             == truth).all(-1))  # fmt: skip
    return {
        "mode right": float(right.float().mean()),
        "radius rule": float((taken <= RADIUS * posterior_scale(sigma)).float().mean()),
        "action rule": float(action_rule.mean()),
        "action rule where right": float(action_rule[right].mean()),
        "action rule where wrong": float(action_rule[~right].mean()) if (~right).any() else 0.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+")
    for run in parser.parse_args().runs:
        print(run, " ".join(f"{k}: {100 * v:.1f}%" for k, v in check(run).items()))


if __name__ == "__main__":
    main()
