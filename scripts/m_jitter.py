"""Where M's draws go wide: the spread of M's prediction against the spread of the next state.

A fresh image of a macrostate lies somewhere in that macrostate's cloud of V's latents; its
fragments are drawn anew at every step, so the next image's place in the next cloud does not
depend on this one's. A world model that knew this would predict the same next state from every
image of a macrostate. This script measures, for an agent's M, on each non-terminal transition
(s, a) of its task:

- the *cloud*: the per-dimension spread of V's latents (M's training targets: draws of
  N(mu, sigma), or V's means for ``model_latents: mu``) over fresh images of the next
  macrostate;
- the *jitter*: the per-dimension spread of M's most likely next state over fresh images of
  s (M fed, as in training, a draw of each image's posterior, or its mean);
- M's *scales*: the heaviest component's sigma (with a full covariance, the root of its
  covariance's diagonal) at the reference latent of s, the input `imagine evaluate` uses;

and how often M's draw is right when M is fed fresh images instead of the reference latent.
Scales near sqrt(cloud^2 + jitter^2) mean that M's likelihood paid for its own jitter.

    .venv/bin/python scripts/m_jitter.py RUN [RUN ...] [--images 16]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.rules import (
    N_ACTIONS,
    all_macrostates,
    apply_actions,
    is_terminal,
    macrostate_index,
)
from imagine.learning.agent import load_agent
from imagine.models.world_model import mixture_mode, scale_tril


def fresh_latents(agent, composer, states: np.ndarray, images: int, rng, sample: bool):
    """(len(states), images, D) latents of fresh images of each state (V's means, or a draw
    of each image's posterior when ``sample``)."""
    repeated = np.repeat(states, images, axis=0)
    mu, sigma = agent.encoder.encode(composer.sample(rng, repeated), repeated)
    if sample:
        mu = mu + sigma * torch.randn(mu.shape, generator=torch.Generator().manual_seed(1))
    return mu.view(len(states), images, -1)


@torch.no_grad()
def measure(agent, images: int, model=None, sample: bool | None = None) -> dict[str, float]:
    """The cloud, jitter and scales (per dimension) and the share of right draws from fresh
    images, for the agent's M or another ``model`` (a WorldModel) in the agent's V; M fed
    posterior draws (``sample``) or V's means, by default as the agent's M learned."""
    task = agent.config.task
    mdn = (model or agent.model).mdn.eval()
    if sample is None:
        sample = agent.config.model_latents == "sample"
    composer = make_composer()
    rng = np.random.default_rng(0)
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    seen = ~is_terminal(states, task)
    states, actions = states[seen], actions[seen]
    nexts = apply_actions(states, actions)
    inputs = fresh_latents(agent, composer, states, images, rng, sample)
    targets = fresh_latents(agent, composer, nexts, images, rng, sample)
    a = torch.as_tensor(actions).repeat_interleave(images)
    flat = inputs.reshape(-1, inputs.shape[-1])
    mixture = mdn(flat, a)
    modes = mixture_mode(mixture).view(inputs.shape)
    draws = mdn.sample(flat, a, torch.Generator().manual_seed(0))
    truth = np.repeat(nexts, images, axis=0)
    right = (agent.encoder.classify(draws).numpy() == truth).all(-1)
    reference = agent.encoder.state_latents()
    at_reference = mdn(reference[torch.as_tensor(macrostate_index(states))],
                       torch.as_tensor(actions))  # fmt: skip
    heaviest = at_reference.log_pi.argmax(-1)
    rows = torch.arange(len(states))
    factor = scale_tril(at_reference)[rows, heaviest]
    scales = (factor @ factor.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).sqrt()
    cloud = targets.std(1).mean(0)
    jitter = modes.std(1).mean(0)
    return {
        "cloud": cloud,
        "jitter": jitter,
        "scales": scales.mean(0),
        "draws right from fresh images": float(right.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--images", type=int, default=16)
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        m = measure(load_agent(run), args.images)
        print(f"{run}: draws right from fresh images {m['draws right from fresh images']:.1%}")
        for key in ("cloud", "jitter", "scales"):
            print(f"  {key:7s} " + " ".join(f"{x:.3f}" for x in m[key].tolist()))
        both = (m["cloud"].square() + m["jitter"].square()).sqrt()
        print("  sqrt(cloud^2 + jitter^2) " + " ".join(f"{x:.3f}" for x in both.tolist()))


if __name__ == "__main__":
    main()
