"""1000 greedy test episodes through V on trained agents: seconds, and where they go (issue 18).

    .venv/bin/python benchmarks/evaluation_speed.py RUN [RUN ...] [--threads 2] [--repeats 3]

For each trained GesturePuzzle agent (a run folder of `imagine train`), times
``greedy_success`` as `imagine evaluate` runs it (the vector environment holds an ended test
episode: only the running ones are stepped and drawn) against the reference measured in the
same process, the loop as it was before (every sub-environment stepped until the last episode
ends, the ended ones reset in the same step), alternating the two ``--repeats`` times; checks
that both give the same successes and returns; and splits the time into V (the encoder's
calls) and the rest. Prints the best time of each.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from gymnasium.vector import AutoresetMode

from imagine.envs.gesture_puzzle.evaluation import greedy_success, policy_success
from imagine.learning.agent import greedy_actions, load_agent


class TimedEncoder:
    """The agent's encoder, with the seconds spent in it counted."""

    def __init__(self, inner) -> None:
        self.inner, self.seconds = inner, 0.0

    def encode(self, images, states):
        start = time.perf_counter()
        out = self.inner.encode(images, states)
        self.seconds += time.perf_counter() - start
        return out


def reference_success(controller, encoder, task: str, episodes: int, seed: int, p: float):
    """The loop before holding ended episodes: every sub-environment stepped (SAME_STEP)."""
    return policy_success(
        lambda obs, states, rows: greedy_actions(controller, encoder, obs, states), task, episodes,
        seed, hand_switch_prob=p, autoreset_mode=AutoresetMode.SAME_STEP,
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{args.episodes} greedy test episodes, {args.threads} thread(s), best of "
          f"{args.repeats}; seconds (of which V)")  # fmt: skip
    print("| run | success | today | before | today / before |")
    print("| --- | --- | --- | --- | --- |")
    for run in args.runs:
        agent = load_agent(run)
        c = agent.config
        timed = TimedEncoder(agent.encoder)
        best = {"today": (np.inf, 0.0), "before": (np.inf, 0.0)}
        results = {}
        for _ in range(args.repeats):
            for name in ("today", "before"):
                timed.seconds = 0.0
                start = time.perf_counter()
                if name == "today":
                    r = greedy_success(agent.controller, timed, c.task, args.episodes, args.seed,
                                       hand_switch_prob=c.hand_switch_prob)  # fmt: skip
                else:
                    r = reference_success(agent.controller, timed, c.task, args.episodes,
                                          args.seed, c.hand_switch_prob)  # fmt: skip
                seconds = time.perf_counter() - start
                results[name] = (r["success"], r["mean_return"])
                if seconds < best[name][0]:
                    best[name] = (seconds, timed.seconds)
        if results["today"] != results["before"]:
            raise SystemExit(f"{run}: results differ: {results}")
        (t, tv), (b, bv) = best["today"], best["before"]
        print(f"| {run} | {100 * results['today'][0]:.1f}% | {t:.2f} ({tv:.2f}) | "
              f"{b:.2f} ({bv:.2f}) | {t / b:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
