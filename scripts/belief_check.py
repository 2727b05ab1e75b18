"""C's belief on finished agents (issue 14, round 11): the same C and M, the same 1000 test
episodes (the studies' EVAL_SEED), acting on V's means, on the belief filtered through M at
several weights w, and (a diagnosis, never a result) on the mean latent of the true macrostate.

    .venv/bin/python scripts/belief_check.py runs/study15/s50/hard-{0,1,2,3,4} --weights 0.5,0.67
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from imagine.envs.gesture_puzzle.evaluation import greedy_success, policy_success
from imagine.envs.gesture_puzzle.rules import macrostate_index
from imagine.learning.agent import belief_tracker, load_agent
from imagine.study.experiments import EVAL_SEED


def true_state_policy(controller, means: torch.Tensor):
    """C's greedy action on the mean latent of each observation's true macrostate."""

    def act(obs, states, rows):
        with torch.no_grad():
            return controller(means[torch.as_tensor(macrostate_index(states))]).argmax(-1).numpy()

    return act


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--weights", default="0.5")
    parser.add_argument("--episodes", type=int, default=1000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    weights = [float(w) for w in args.weights.split(",")]
    head = ["V's means"] + [f"belief, w = {w}" for w in weights] + ["true state's mean latent"]
    print("| run | " + " | ".join(head) + " |")
    print("| --- " * (len(head) + 1) + "|")
    for run in args.runs:
        agent = load_agent(run)
        c, n = agent.config, args.episodes
        p = c.hand_switch_prob
        cells = [greedy_success(agent.controller, agent.encoder, c.task, n, EVAL_SEED,
                                hand_switch_prob=p)["success"]]  # fmt: skip
        for w in weights:
            agent.config = dataclasses.replace(c, belief="filtered", belief_weight=w)
            cells.append(greedy_success(agent.controller, agent.encoder, c.task, n, EVAL_SEED,
                                        hand_switch_prob=p,
                                        belief=belief_tracker(agent, n))["success"])  # fmt: skip
        agent.config = c
        on_means = true_state_policy(agent.controller, agent.encoder.state_latents())
        cells.append(policy_success(on_means, c.task, n, EVAL_SEED, hand_switch_prob=p)["success"])
        print(f"| {run} | " + " | ".join(f"{100 * x:.1f}" for x in np.array(cells)) + " |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
