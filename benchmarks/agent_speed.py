"""Milliseconds per real time step of Algorithm 1, on one core.

For baseline and augmented under `fast` and `paper` (oracle encoder, so vision does not count;
V adds about 0.7 ms per step, see vae_speed.py), once M_R holds a batch of (random) transitions:
each agent runs with imagination on from the first episode, and the time of ``--steps`` steps is
divided by their number. The reference measured in the same run is a float32 matrix product.

    .venv/bin/python benchmarks/agent_speed.py [--steps 300]
"""

from __future__ import annotations

import argparse
import time

import torch

from imagine.agent import Agent
from imagine.config import agent_preset
from imagine.encoder import OracleEncoder


def ms_per_step(preset: str, method: str, steps: int) -> float:
    config = agent_preset(preset, encoder="oracle", method=method, imagination_start=0,
                          episodes=10**6)  # fmt: skip
    agent = Agent(config, OracleEncoder())
    n, d = config.model_batch, agent.encoder.latent_dim
    agent.real.add(  # M_R needs a batch's worth before the first update; the cost is the same
        mu=torch.randn(n, d), sigma=torch.full((n, d), 0.05), action=torch.randint(6, (n,)),
        next_mu=torch.randn(n, d), next_sigma=torch.full((n, d), 0.05),
        reward=torch.full((n,), -1.0), done=torch.zeros(n),
    )  # fmt: skip
    start_t, start = agent.t, time.perf_counter()
    while agent.t - start_t < steps:
        agent.run_episode()
    return 1000 * (time.perf_counter() - start) / (agent.t - start_t)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    torch.set_num_threads(1)
    n = 1024
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    start = time.perf_counter()
    for _ in range(5):
        a @ b
    peak = 5 * 2 * n**3 / (time.perf_counter() - start)
    print(f"reference: float32 {n}x{n} matmul, 1 thread: {peak / 1e9:.1f} GFLOP/s")
    for preset in ("fast", "paper"):
        for method in ("baseline", "augmented"):
            steps = args.steps if preset == "fast" else max(20, args.steps // 10)
            ms = ms_per_step(preset, method, steps)
            print(f"{preset:6s} {method:10s} {ms:8.2f} ms per real step")


if __name__ == "__main__":
    main()
