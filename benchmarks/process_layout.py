"""On a two-core machine, which layout trains the most agent steps per second: two processes of
one thread each (what `imagine reproduce` and the studies run here), one process with two
threads, or larger populations (issue 18: why two processes each run at about 60% of one alone,
and whether one process with two threads or a larger population does better).

Every layout trains `fast` augmented populations (today's preset: K = 5 MDNs, the mask gate,
value expansion; oracle encoder and imagination from the first step, as
``population_speed.py``) for ``--steps`` lockstep steps after two warm-up steps, and the row is
the whole machine's agent steps per second:

- one process, one thread, P agents: one core alone (the reference for the two processes);
- two processes at once, one thread and P agents each (they start timing together);
- one process, two threads, 2P agents; one process, two threads, P agents;
- one process, one thread, 2P agents (a larger population on one core).

Layouts alternate ``--repeats`` times in one run; the table gives each one's best and its
ratio to the two processes'. Run it on an otherwise idle machine.

    .venv/bin/python benchmarks/process_layout.py [--agents 5] [--steps 20] [--repeats 2]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from population_speed import population


def rate(agents: int, threads: int, steps: int, barrier=None) -> float:
    """Agent steps per second of one population of ``agents`` on ``threads`` threads."""
    torch.set_num_threads(threads)
    pop = population("fast", agents)
    for _ in range(2):
        pop.step()
    if barrier is not None:
        barrier.wait()
    start = time.perf_counter()
    for _ in range(steps):
        pop.step()
    return agents * steps / (time.perf_counter() - start)


def _worker(agents: int, steps: int, barrier, out) -> None:
    out.put(rate(agents, 1, steps, barrier))


def two_processes(agents: int, steps: int) -> float:
    """Both processes' agent steps per second together (each one thread, timed from a
    common start)."""
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(2), ctx.Queue()
    workers = [ctx.Process(target=_worker, args=(agents, steps, barrier, out)) for _ in range(2)]
    for w in workers:
        w.start()
    rates = [out.get() for _ in workers]
    for w in workers:
        w.join()
    return sum(rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=5, help="P")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    P, steps = args.agents, args.steps
    layouts = {
        f"one process, 1 thread, {P} agents (one core alone)": lambda: rate(P, 1, steps),
        f"two processes, 1 thread and {P} agents each": lambda: two_processes(P, steps),
        f"one process, 2 threads, {2 * P} agents": lambda: rate(2 * P, 2, steps),
        f"one process, 2 threads, {P} agents": lambda: rate(P, 2, steps),
        f"one process, 1 thread, {2 * P} agents": lambda: rate(2 * P, 1, steps),
    }
    best = {name: 0.0 for name in layouts}
    for r in range(args.repeats):
        for name, run in layouts.items():
            got = run()
            best[name] = max(best[name], got)
            print(f"repeat {r + 1}: {name}: {got:.1f} agent steps/s", flush=True)
    two = best[f"two processes, 1 thread and {P} agents each"]
    alone = best[f"one process, 1 thread, {P} agents (one core alone)"]
    print()
    print(f"| layout (best of {args.repeats}, {steps} steps) | agent steps/s, whole machine | "
          "/ two processes |")  # fmt: skip
    print("| --- | --- | --- |")
    for name, value in best.items():
        print(f"| {name} | {value:.1f} | {value / two:.2f}x |")
    print(f"\neach of the two processes at {two / 2 / alone:.0%} of one core alone")


if __name__ == "__main__":
    main()
