"""Test episodes in any environment (:mod:`imagine.envs`): mean return with its 95% interval,
and the success rate where the environment says when a goal is reached.

``episodes`` episodes run on ``copies`` copies of the environment at once (a Gymnasium vector
env, autoreset disabled); test episode k starts from ``reset(seed=...)`` with a seed drawn from
(``seed``, k), so the same seed gives the same episodes whatever the number of copies.
GesturePuzzle's own test (1000 episodes in one batch, the paper's success rate) is
:func:`imagine.envs.gesture_puzzle.evaluation.greedy_success`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from imagine.envs.spec import EnvSpec, episode_seed, reset_ended
from imagine.intervals import mean_interval, wilson_interval

Policy = Callable[[np.ndarray, Any, np.ndarray], np.ndarray]
"""Actions, int64 (N,), for N observations as the spec hands them to an encoder (x, extra),
and the copies (N,) they come from. A policy with a ``restart(copies)`` method is told which
copies start a new episode (:class:`GreedyPolicy`'s belief)."""


@torch.no_grad()
def run_episodes(
    spec: EnvSpec, policy: Policy, episodes: int, seed: int, copies: int = 64
) -> dict[str, float]:
    """``episodes`` episodes of ``policy``: mean return (95% interval), episode length, and
    success (Wilson 95% interval) when the environment reports it."""
    copies = min(copies, episodes)
    envs = spec.make_vector_env(copies)
    returns, lengths = np.zeros(episodes), np.zeros(episodes)  # by test episode
    successes = np.zeros(episodes, dtype=bool)
    cut = np.zeros(episodes, dtype=bool)  # ended by the time limit, not by the environment
    reported = False
    episode_of = np.arange(copies)  # the test episode each copy runs (>= episodes: idle)
    seeds = [episode_seed(seed, int(k)) for k in episode_of]
    obs, info = envs.reset(seed=seeds)
    total = np.zeros(copies)
    length = np.zeros(copies, dtype=np.int64)
    won = np.zeros(copies, dtype=bool)
    actions = np.zeros(copies, dtype=np.int64)
    while (episode_of < episodes).any():
        live = np.flatnonzero(episode_of < episodes)
        x, extra = spec.encoder_input(obs, info)
        actions[live] = policy(x[live], None if extra is None else extra[live], live)
        obs, reward, terminated, truncated, info = envs.step(actions)
        total += reward
        length += 1
        success = spec.success(reward, info)
        if success is not None:
            reported = True
            won |= success
        ended = terminated | truncated  # idle copies too: a vector env steps every copy
        if not ended.any():
            continue
        done = np.flatnonzero(ended & (episode_of < episodes))
        k = episode_of[done]
        returns[k], lengths[k], successes[k] = total[done], length[done], won[done]
        cut[k] = truncated[done] & ~terminated[done]
        episode_of[done] = episode_of.max() + 1 + np.arange(len(done))
        obs, info = reset_ended(envs, ended, episode_of, seed)
        if hasattr(policy, "restart"):
            policy.restart(np.flatnonzero(ended))
        done = np.flatnonzero(ended)
        total[done], length[done], won[done] = 0.0, 0, False
    envs.close()
    low, high = mean_interval(returns)
    out = {"mean_return": float(returns.mean()), "return_ci_low": low,
           "return_ci_high": high, "mean_length": float(lengths.mean()),
           "truncated": float(cut.mean()), "episodes": episodes}  # fmt: skip
    if reported:
        n = int(successes.sum())
        s_low, s_high = wilson_interval(n, episodes)
        out |= {"success": n / episodes, "ci_low": s_low, "ci_high": s_high}
    return out


class GreedyPolicy:
    """C's greedy actions on the encoder's mu, or on the beliefs of ``belief`` (a tracker
    with a row per copy, :func:`imagine.learning.agent.belief_tracker`)."""

    def __init__(self, controller, encoder, belief=None) -> None:
        self.controller, self.encoder, self.belief = controller, encoder, belief

    def __call__(self, x, extra, copies: np.ndarray) -> np.ndarray:
        from imagine.learning.agent import greedy_actions

        return greedy_actions(self.controller, self.encoder, x, extra, self.belief, copies)

    def restart(self, copies: np.ndarray) -> None:
        if self.belief is not None:
            self.belief.restart(torch.as_tensor(copies))


def greedy_policy(controller, encoder, belief=None) -> GreedyPolicy:
    """C's greedy actions (:class:`GreedyPolicy`)."""
    return GreedyPolicy(controller, encoder, belief)


def agent_policy(agent, episodes: int, copies: int = 64) -> GreedyPolicy:
    """An agent's greedy policy for :func:`run_episodes` (``episodes`` on ``copies``, the
    same ``copies`` as run_episodes'): on its filtered belief where it acts on one."""
    from imagine.learning.agent import belief_tracker

    belief = belief_tracker(agent, min(copies, episodes))
    return GreedyPolicy(agent.controller, agent.encoder, belief)


@torch.no_grad()
def circling(
    spec: EnvSpec,
    policy: Policy,
    episodes: int,
    seed: int,
    window: int = 200,
    tolerance: float = 0.05,
) -> dict[str, float]:
    """Whether a policy's time-limited episodes circle: in a deterministic environment a
    greedy policy can fall into a cycle of states that never ends the episode. Each of
    ``episodes`` test episodes (the seeds of :func:`run_episodes`) runs alone on a vector
    observation; an episode that the time limit cuts *circles* when its last observation
    comes back within ``tolerance`` of a typical step's length (the mean over its last
    ``window`` steps) to one of its last ``window`` observations; its period is that lag (1:
    a state it no longer leaves). Returns the share of episodes cut, the share of those that
    circle, the median period, and ``one_action``: the mean share of its most frequent action
    in a cut episode (1.0: the policy does one thing whatever it sees)."""
    cut, periods, one_action = 0, [], []
    for k in range(episodes):
        envs = spec.make_vector_env(1)
        obs, info = envs.reset(seed=[episode_seed(seed, k)])
        if hasattr(policy, "restart"):
            policy.restart(np.array([0]))
        seen, taken = [np.asarray(obs[0], dtype=np.float64).ravel()], []
        while True:
            x, extra = spec.encoder_input(obs, info)
            action = np.asarray(policy(x, extra, np.array([0])))
            obs, _, terminated, truncated, info = envs.step(action)
            seen.append(np.asarray(obs[0], dtype=np.float64).ravel())
            taken.append(int(action[0]))
            if terminated[0] or truncated[0]:
                break
        envs.close()
        if terminated[0]:
            continue
        cut += 1
        one_action.append(np.bincount(taken).max() / len(taken))
        path = np.array(seen[-(window + 1) :])
        step = np.linalg.norm(np.diff(path, axis=0), axis=1).mean()
        back = np.linalg.norm(path[:-1] - path[-1], axis=1)[::-1]  # lag 1, 2, ...
        close = np.flatnonzero(back <= tolerance * step)  # a fixed point: 0 <= 0
        if len(close):
            periods.append(int(close[0]) + 1)  # the first lag, not a multiple of it
    return {"episodes": episodes, "truncated": cut / episodes,
            "circling": len(periods) / cut if cut else 0.0,
            "median_period": float(np.median(periods)) if periods else float("nan"),
            "one_action": float(np.mean(one_action)) if one_action else float("nan")}  # fmt: skip


class EpsilonGreedy:
    """``policy`` with a uniform random action in its place with probability ``epsilon`` at
    each step (its own generator, seeded): how much a greedy result rests on never deviating.
    In a deterministic environment a greedy C can circle through the same states until the
    time limit, where one random action in a thousand breaks the circle."""

    def __init__(self, policy: Policy, n_actions: int, epsilon: float, seed: int) -> None:
        self.policy, self.n_actions, self.epsilon = policy, n_actions, epsilon
        self.rng = np.random.default_rng(seed)

    def __call__(self, x, extra, copies: np.ndarray) -> np.ndarray:
        actions = np.asarray(self.policy(x, extra, copies))
        deviate = self.rng.random(len(actions)) < self.epsilon
        actions = np.where(deviate, self.rng.integers(self.n_actions, size=len(actions)), actions)
        belief = getattr(self.policy, "belief", None)
        if belief is not None:  # M's filter follows the action taken, not the greedy one
            belief.acted(torch.as_tensor(actions), torch.as_tensor(copies))
        return actions

    def restart(self, copies: np.ndarray) -> None:
        if hasattr(self.policy, "restart"):
            self.policy.restart(copies)


def random_policy(n_actions: int, seed: int) -> Policy:
    """Uniform random actions (the floor every agent must beat)."""
    rng = np.random.default_rng(seed)
    return lambda x, extra, copies: rng.integers(n_actions, size=len(x))
