"""Where a real step's time goes, baseline against augmented, in one run (issue 56's cost model).

    .venv/bin/python benchmarks/step_cost.py [--agents 5] [--steps 100] [--vae runs/vae-fast]
        [--cartpole-steps 300] [--cartpole-agents 1] [--set KEY=VALUE ...]

Two settings, each with the `fast` baseline, the `fast` augmented agent and (with ``--set``) a
candidate augmented agent with those settings over `fast`:

- GesturePuzzle `hard`: a population of ``--agents`` seeds stepping in lockstep, V encoding
  the images (``--vae``; without it the oracle encoder), imagination from the first step;
- CartPole-v1: ``--cartpole-agents`` seeds (one by default), its 4-vector as it is,
  imagination from the first step.

``--steps 0`` leaves out the GesturePuzzle rows, ``--cartpole-steps 0`` the CartPole ones.

Each row is milliseconds per real step (one lockstep step of the population), after a
warm-up, on one torch thread, split by the parts of Algorithm 1 (timers around the
population's own methods): M's full updates (the MDN members with r and d, N_E a step), r and
d alone (``reward_updates``), C on real batches (MVE's expansion included), imagination
(rollouts, the gate and C's N_I updates on M_I), the environment, V (or the vector encoder),
and the rest (acting, M_R). Beside it: the ratio to the baseline of the same setting, the
floating-point operations per real step (``torch.utils.flop_counter``: matrix products and
convolutions, forward and backward) and what share of the machine's fp32 matmul peak the step
reaches (the peak measured in the same run on one thread).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from imagine.config import agent_preset, parse_assignments
from imagine.learning.agent import make_encoder
from imagine.learning.population import Population

PARTS = ["M", "r, d", "C real", "imagination", "env", "V", "rest"]


def timed_population(configs: list, encoder: Any) -> tuple[Population, dict[str, float]]:
    """A population whose parts add their seconds to the returned totals."""
    pop, totals = Population(configs, encoder), defaultdict(float)

    def timer(name: str, function: Callable) -> Callable:
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                totals[name] += time.perf_counter() - start

        return timed

    update = pop.model.update
    pop.model.update = lambda *a, mdn=True, **k: timer("M" if mdn else "r, d", update)(
        *a, mdn=mdn, **k
    )
    pop._learn_from_real = timer("C real", pop._learn_from_real)
    pop._imagine = timer("imagination", pop._imagine)
    pop.envs.step = timer("env", pop.envs.step)
    pop.envs.reset = timer("env", pop.envs.reset)
    pop._encode = timer("V", pop._encode)
    return pop, totals


def measure(pop: Population, totals: dict[str, float], steps: int) -> dict[str, float]:
    """Milliseconds per real step, in all and by part, after a warm-up; then FLOPs per step."""
    for _ in range(20):
        pop.step()
    totals.clear()
    start = time.perf_counter()
    for _ in range(steps):
        pop.step()
    total = time.perf_counter() - start
    parts = {name: 1000 * seconds / steps for name, seconds in totals.items()}
    parts["rest"] = 1000 * total / steps - sum(parts.values())
    counted = max(steps // 5, 8)
    with FlopCounterMode(display=False) as flops:
        for _ in range(counted):
            pop.step()
    return {"total": 1000 * total / steps, "flops": flops.get_total_flops() / counted, **parts}


def matmul_peak(n: int = 1024, repeats: int = 20) -> float:
    """The machine's fp32 matrix-product rate on this thread count, in FLOP/s (best of runs)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * n**3 / best


def settings(args: argparse.Namespace) -> dict[str, tuple[list, Any, int]]:
    """Each row's population configs, encoder and measured steps."""
    candidate = parse_assignments(args.set_) if args.set_ else None
    arms = [("baseline", "baseline", {}), ("augmented (fast)", "augmented", {})]
    if candidate:
        arms.append((f"augmented, {' '.join(args.set_)}", "augmented", candidate))
    encoder = "vae" if args.vae else "oracle"
    rows = {}
    for name, method, extra in arms:
        if args.steps:
            puzzle = [agent_preset("fast", encoder=encoder, vae_run=args.vae, task="hard",
                                   seed=seed, method=method, imagination_start=0,
                                   episodes=10**6, **extra)
                      for seed in range(args.agents)]  # fmt: skip
            rows[f"GesturePuzzle hard, {args.agents} seeds, {encoder} | {name}"] = (
                puzzle,
                make_encoder(puzzle[0]),
                args.steps,
            )
        if args.cartpole_steps:
            pole = [agent_preset("fast", env="CartPole-v1", encoder="vector", method=method,
                                 seed=seed, imagination_start=0, episodes=10**6, **extra)
                    for seed in range(args.cartpole_agents)]  # fmt: skip
            rows[f"CartPole-v1, {args.cartpole_agents} seed(s) | {name}"] = (
                pole,
                make_encoder(pole[0]),
                args.cartpole_steps,
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=5)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--cartpole-steps", type=int, default=300, help="0: no CartPole rows")
    parser.add_argument("--cartpole-agents", type=int, default=1)
    parser.add_argument("--vae", default=None, help="V run folder (default: the oracle)")
    parser.add_argument("--set", dest="set_", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    torch.set_num_threads(1)
    peak = matmul_peak()
    results = {}
    for name, (configs, encoder, steps) in settings(args).items():
        pop, totals = timed_population(configs, encoder)
        results[name] = measure(pop, totals, steps)
    print(f"ms per real step, one thread; fp32 matmul peak {peak / 1e9:.1f} GFLOP/s")
    print("| setting | agent | total | x baseline | " + " | ".join(PARTS)
          + " | MFLOP a step | % of peak |")  # fmt: skip
    print("| --- " * (len(PARTS) + 6) + "|")
    for name, r in results.items():
        setting, agent = name.split(" | ")
        base = results[f"{setting} | baseline"]["total"]
        cells = [f"{r.get(p, 0.0):.1f}" for p in PARTS]
        share = 100 * r["flops"] / (r["total"] / 1000) / peak
        print(f"| {setting} | {agent} | {r['total']:.1f} | {r['total'] / base:.1f} | "
              + " | ".join(cells) + f" | {r['flops'] / 1e6:.1f} | {share:.1f} |")  # fmt: skip


if __name__ == "__main__":
    main()
