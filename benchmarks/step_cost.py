"""Where a real step's time goes, baseline against augmented, in one run (issue 56's cost model).

    .venv/bin/python benchmarks/step_cost.py [--agents 3] [--steps 100] [--set KEY=VALUE ...]

Populations of `fast` agents on `hard` (oracle encoder, imagination from the first step, one
torch thread) step ``--steps`` lockstep steps after a warm-up. For each, the milliseconds per
population step, split by the parts of Algorithm 1 (timers around the population's own
methods): M's full updates (the MDN members with r and d, N_E a step), r and d alone
(``reward_updates``), C on real batches (MVE's expansion included), imagination (rollouts, the
gate and C's N_I updates on M_I), and the rest (acting, the environment, M_R). Printed with
each population's ratio to the baseline measured in the same run. ``--set`` adds a candidate
augmented agent with those settings over `fast`.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch

from imagine.config import agent_preset, parse_assignments
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.learning.population import Population


def timed_population(agents: int, method: str, **overrides) -> tuple[Population, dict]:
    """A population whose parts add their seconds to the returned totals."""
    configs = [agent_preset("fast", encoder="oracle", task="hard", seed=seed, method=method,
                            imagination_start=0, episodes=10**6, **overrides)
               for seed in range(agents)]  # fmt: skip
    pop, totals = Population(configs, OracleEncoder()), defaultdict(float)

    def timer(name, function):
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
    return pop, totals


def measure(pop: Population, totals: dict, steps: int) -> dict[str, float]:
    """Milliseconds per population step, in all and by part, after a warm-up."""
    for _ in range(20):
        pop.step()
    totals.clear()
    start = time.perf_counter()
    for _ in range(steps):
        pop.step()
    total = time.perf_counter() - start
    parts = {name: 1000 * seconds / steps for name, seconds in totals.items()}
    parts["rest"] = 1000 * total / steps - sum(parts.values())
    return {"total": 1000 * total / steps, **parts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=3)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--set", dest="set_", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = {"baseline": timed_population(args.agents, "baseline"),
            "augmented (fast)": timed_population(args.agents, "augmented")}  # fmt: skip
    if args.set_:
        rows[f"augmented, {' '.join(args.set_)}"] = timed_population(
            args.agents, "augmented", **parse_assignments(args.set_)
        )
    results = {name: measure(pop, totals, args.steps) for name, (pop, totals) in rows.items()}
    parts = ["M", "r, d", "C real", "imagination", "rest"]
    print(f"ms per step of a population of {args.agents} (`hard`, oracle, {args.steps} steps)")
    print("| agent | total | x baseline | " + " | ".join(parts) + " |")
    print("| --- " * (len(parts) + 3) + "|")
    base = results["baseline"]["total"]
    for name, r in results.items():
        cells = [f"{r.get(p, 0.0):.1f}" for p in parts]
        print(
            f"| {name} | {r['total']:.1f} | {r['total'] / base:.1f} | " + " | ".join(cells) + " |"
        )


if __name__ == "__main__":
    main()
