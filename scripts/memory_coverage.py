"""How much of the task the real memory M_R already covers: is C short of data or of updates?
(issue 14).

    .venv/bin/python scripts/memory_coverage.py RUN [RUN ...]

For each run (its last checkpoint), reads every real transition's start state with V's latent
classifier (which the agent never uses) and counts the distinct non-terminal macrostates and
(macrostate, action) pairs M_R holds, against all the task has (a real transition never starts
from a terminal state). Where M_R already holds nearly every pair, imagination cannot add data
C lacks, only more updates on what it has.
"""

from __future__ import annotations

import argparse

import numpy as np

from imagine.checkpoint import load_tensors
from imagine.envs.gesture_puzzle.rules import (
    N_ACTIONS,
    all_macrostates,
    is_terminal,
    macrostate_index,
)
from imagine.learning.agent import load_agent


def coverage(run: str) -> dict[str, float]:
    agent = load_agent(run)
    tensors = load_tensors(f"{run}/agent.safetensors")
    states = agent.encoder.classify(tensors["real.mu"]).numpy()
    legal = ~is_terminal(states, agent.config.task)  # the few the classifier misreads left out
    index = macrostate_index(states[legal])
    pairs = index * N_ACTIONS + tensors["real.action"].numpy()[legal]
    non_terminal = int((~is_terminal(all_macrostates(), agent.config.task)).sum())
    return {
        "transitions": len(states),
        "states": len(np.unique(index)),
        "all_states": non_terminal,
        "pairs": len(np.unique(pairs)),
        "all_pairs": non_terminal * N_ACTIONS,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+")
    args = parser.parse_args()
    print("| run | real transitions | non-terminal states seen | (state, action) pairs seen |")
    print("| --- | --- | --- | --- |")
    for run in args.runs:
        c = coverage(run)
        share = 100 * c["pairs"] / c["all_pairs"]
        print(f"| {run} | {c['transitions']} | {c['states']} / {c['all_states']} | "
              f"{c['pairs']} / {c['all_pairs']} ({share:.0f}%) |")  # fmt: skip


if __name__ == "__main__":
    main()
