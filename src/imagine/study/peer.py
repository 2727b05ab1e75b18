"""Stable-Baselines3's DQN on GesturePuzzle: a peer row of ``imagine reproduce``'s tables
(``--baselines sb3``; issue 16).

A reader knows SB3's DQN; this row shows our baseline against it on the same task, budgets and
test episodes. Per (task, seed), SB3's DQN learns from the same observations (64 x 64 RGB
images, its ``CnnPolicy``: the Nature DQN network) with SB3's default hyperparameters, except a
replay buffer no larger than the run; its exploration schedule runs over the largest episode
budget's longest possible run (``MAX_EPISODE_ACTIONS`` steps per episode), so it does not depend
on which budgets are asked. When its episode count reaches a budget, its greedy policy plays
the same ``eval_episodes`` test episodes as our agents
(:func:`~imagine.envs.gesture_puzzle.evaluation.policy_success`, seed ``EVAL_SEED``), and the
result is written as ``OUT/sb3-dqn/<task>-<seed>/evaluation-NNNNN.json`` in our evaluations'
format, method ``sb3-dqn``. A finished budget is never run again; an unfinished run starts over
(SB3 keeps no checkpoint here).

SB3 is an optional extra (``pip install 'imagine[sb3]'``); without it the row is skipped with a
one-line message.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym

from imagine import ENV_ID
from imagine.checkpoint import read_json, write_json
from imagine.envs.gesture_puzzle.rules import MAX_EPISODE_ACTIONS
from imagine.study.compare import sb3_available, without_log_folder

METHOD = "sb3-dqn"
BASELINES = ("sb3",)
"""Peer baselines ``imagine reproduce --baselines`` can add."""


def evaluation_path(folder: Path, budget: int) -> Path:
    return folder / f"evaluation-{budget:05d}.json"


def settings(budgets: Sequence[int]) -> dict[str, Any]:
    """SB3's DQN settings: its defaults, with a replay buffer no larger than the longest run."""
    return {"buffer_size": min(1_000_000, MAX_EPISODE_ACTIONS * max(budgets))}


def train_peer(
    task: str,
    seed: int,
    budgets: Sequence[int],
    folder: Path,
    eval_episodes: int,
    eval_seed: int,
    hand_switch_prob: float = 0.0,
    log: Callable[[str], None] = print,
) -> None:
    """SB3's DQN on ``task`` to the largest budget (in episodes), evaluated at each budget."""
    from stable_baselines3 import DQN

    todo = sorted(b for b in budgets if not evaluation_path(folder, b).is_file())
    if not todo:
        return
    log(f"sb3-dqn: {task} seed {seed} to {max(todo)} episodes")
    horizon = MAX_EPISODE_ACTIONS * max(budgets)
    env = gym.make(ENV_ID, task=task, hand_switch_prob=hand_switch_prob)
    model = without_log_folder(DQN("CnnPolicy", env, seed=seed, device="cpu", verbose=0,
                                   **settings(budgets)))  # fmt: skip
    values = {"task": task, "method": METHOD, "seed": seed, "settings": settings(budgets),
              "horizon_steps": horizon}  # fmt: skip
    evaluate = _budget_callback(folder, todo, eval_episodes, eval_seed, hand_switch_prob, values)
    model.learn(total_timesteps=horizon, callback=evaluate)
    env.close()


def _budget_callback(folder: Path, budgets: list[int], eval_episodes: int, eval_seed: int,
                     hand_switch_prob: float, values: dict[str, Any]):  # fmt: skip
    """An SB3 callback: counts finished episodes; at each budget, the greedy policy through
    the test episodes; stops learning after the largest."""
    from stable_baselines3.common.callbacks import BaseCallback

    from imagine.envs.gesture_puzzle.evaluation import policy_success

    class Evaluate(BaseCallback):
        episodes = 0

        def _on_step(self) -> bool:
            self.episodes += int(self.locals["dones"].sum())
            if self.episodes in budgets and not evaluation_path(folder, self.episodes).is_file():
                model = self.model
                result = policy_success(
                    lambda obs, states, rows: model.predict(obs, deterministic=True)[0],
                    values["task"], eval_episodes, eval_seed, hand_switch_prob=hand_switch_prob,
                )  # fmt: skip
                write_json(evaluation_path(folder, self.episodes),
                           {**values, "budget": self.episodes, "time_steps": self.num_timesteps,
                            **result})  # fmt: skip
            return self.episodes < max(budgets)

    return Evaluate()


def peer_folder(out: Path, task: str, seed: int) -> Path:
    return out / METHOD / f"{task}-{seed}"


def run_peers(
    baselines: Sequence[str],
    out: Path,
    tasks: Sequence[str],
    seeds: Sequence[int],
    budgets: Sequence[int],
    eval_episodes: int,
    eval_seed: int,
    hand_switch_prob: float = 0.0,
    log: Callable[[str], None] = print,
) -> None:
    """Train and evaluate the asked peer baselines (or say in one line why not)."""
    if "sb3" not in baselines:
        return
    if not sb3_available():
        log("sb3-dqn row skipped: Stable-Baselines3 is not installed (pip install 'imagine[sb3]')")
        return
    for task in tasks:
        for seed in seeds:
            train_peer(task, seed, budgets, peer_folder(out, task, seed), eval_episodes,
                       eval_seed, hand_switch_prob, log)  # fmt: skip


def peer_evaluations(out: Path, tasks: Sequence[str], seeds: Sequence[int],
                     budgets: Sequence[int]) -> list[dict[str, Any]]:  # fmt: skip
    """The peers' evaluations written so far for these tasks, seeds and budgets."""
    paths = [evaluation_path(peer_folder(out, t, s), b) for t in tasks for s in seeds
             for b in budgets]  # fmt: skip
    return [read_json(p, "evaluation") for p in paths if p.is_file()]
