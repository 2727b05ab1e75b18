"""How right are M's one-step predictions from real observations of start states: the most
likely next state against a sample (what imagination uses), and the MDN's predicted scales.

    .venv/bin/python scripts/m_sample_quality.py RUN [--n 2000]

The diagnostic behind the `fast` preset's dropout 0 in M (README, "Presets").
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.rules import apply_actions, start_states
from imagine.learning.agent import load_agent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--n", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    agent = load_agent(args.run)
    encoder, model = agent.encoder, agent.model
    rng = np.random.default_rng(0)
    starts = start_states(agent.config.task)
    states = starts[rng.integers(0, len(starts), args.n)]
    mu, sigma = encoder.encode(make_composer().sample(rng, states), states)
    actions = torch.as_tensor(rng.integers(0, 6, args.n))
    truth = apply_actions(states, actions.numpy())
    generator = torch.Generator().manual_seed(0)
    model.eval()
    with torch.no_grad():
        z = mu + sigma * torch.randn(mu.shape, generator=generator)
        likely = model.mdn.most_likely(mu, actions)
        sampled = model.mdn.sample(z, actions, generator)
        mixture = model.mdn(mu, actions)
        top = mixture.log_pi.argmax(-1)
        scales = mixture.sigma[torch.arange(args.n), top].mean(0)

    def right(latents: torch.Tensor) -> float:
        return float((encoder.classify(latents).numpy() == truth).all(-1).mean())

    print(f"{args.run}: {args.n} transitions from start states")
    print(f"  start states read right:             {right_start(encoder, mu, states):.3f}")
    print(f"  most likely next state right:        {right(likely):.3f}")
    print(f"  sampled next state right:            {right(sampled):.3f}")
    print(f"  V's posterior sigma per dimension:   {np.round(sigma.mean(0).numpy(), 3)}")
    print(f"  M's predicted scale per dimension:   {np.round(scales.numpy(), 3)}")


def right_start(encoder, mu: torch.Tensor, states: np.ndarray) -> float:
    return float((encoder.classify(mu).numpy() == states).all(-1).mean())


if __name__ == "__main__":
    main()
