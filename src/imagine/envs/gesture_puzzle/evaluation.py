"""Judging an agent: greedy test episodes in the vectorized environment, and M's accuracy over
all 192 x 6 true transitions (docs/design.md section 3)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from scipy.stats import rankdata

from imagine.envs.gesture_puzzle.rules import (
    N_ACTIONS,
    REWARD_GOAL,
    REWARD_ILLEGAL,
    REWARD_STEP,
    all_macrostates,
    apply_actions,
    is_terminal,
    macrostate_index,
    rewards,
)
from imagine.envs.gesture_puzzle.vector import GesturePuzzleVectorEnv
from imagine.intervals import mean_interval, wilson_interval
from imagine.learning.agent import greedy_actions
from imagine.learning.belief import BeliefTracker
from imagine.learning.gate import gate_threshold, gate_transitions, support_distance
from imagine.learning.imagination import actions_at, imagine_rollouts, posterior_scale
from imagine.models.controller import Controller, PopulationController
from imagine.models.world_model import PopulationWorldModel, WorldModel


@torch.no_grad()
def greedy_success(
    controller: Controller,
    encoder,
    task: str,
    episodes: int,
    seed: int,
    composer=None,
    hand_switch_prob: float = 0.0,
    belief: BeliefTracker | None = None,
) -> dict[str, float]:
    """Run ``episodes`` greedy test episodes at once; success = the episode reached a goal.
    C acts on V's means, or on the beliefs of ``belief`` (a tracker of ``episodes`` rows,
    :func:`imagine.learning.agent.belief_tracker`)."""
    return policy_success(
        lambda obs, states, rows: greedy_actions(controller, encoder, obs, states, belief, rows),
        task, episodes, seed, composer, hand_switch_prob,
    )  # fmt: skip


def agent_success(agent, episodes: int, seed: int) -> dict[str, float]:
    """A trained agent's greedy test episodes (:func:`greedy_success`, its task and human), on
    its belief where it acts on one (:func:`imagine.learning.agent.belief_tracker`); then also
    ``success_observation``: the same agent on V's means alone."""
    from imagine.learning.agent import belief_tracker

    c, belief = agent.config, belief_tracker(agent, episodes)

    def run(belief):
        return greedy_success(agent.controller, agent.encoder, c.task, episodes, seed,
                              hand_switch_prob=c.hand_switch_prob, belief=belief)  # fmt: skip

    result = run(belief)
    if belief is not None:
        result["success_observation"] = run(None)["success"]
    return result


@torch.no_grad()
def policy_success(
    policy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    task: str,
    episodes: int,
    seed: int,
    composer=None,
    hand_switch_prob: float = 0.0,
    autoreset_mode: AutoresetMode = AutoresetMode.DISABLED,
) -> dict[str, float]:
    """``episodes`` test episodes at once of any ``policy`` (images (N, 64, 64, 3), true
    macrostates (N, 4) and the N episodes' indices -> actions (N,)): success rate with its 95%
    Wilson interval, mean return with its 95% interval. Episode k starts from ``seed + k`` as
    in :func:`greedy_success`, so every agent (ours or a peer's) meets the same test episodes.
    ``autoreset_mode``: DISABLED
    holds an ended episode, so it costs nothing more; SAME_STEP (the loop before, for
    ``benchmarks/evaluation_speed.py``) steps all until the last ends, with the same results."""
    envs = GesturePuzzleVectorEnv(
        episodes, task=task, fragments=None if composer is None else composer.pool,
        autoreset_mode=autoreset_mode, hand_switch_prob=hand_switch_prob,
    )  # fmt: skip
    obs, info = envs.reset(seed=seed)
    states = info["macrostate"]
    running = np.ones(episodes, dtype=bool)
    success = np.zeros(episodes, dtype=bool)
    returns = np.zeros(episodes)
    actions = np.zeros(episodes, dtype=np.int64)
    while running.any():
        live = np.flatnonzero(running)  # only episodes still running need V and C
        actions[live] = policy(obs[live], states[live], live)
        obs, reward, terminated, truncated, info = envs.step(actions)
        returns += np.where(running, reward, 0.0)
        success |= running & (reward == REWARD_GOAL)
        running &= ~(terminated | truncated)
        states = info["macrostate"]
    n = int(success.sum())
    low, high = wilson_interval(n, episodes)
    return_low, return_high = mean_interval(returns)
    return {"success": n / episodes, "ci_low": low, "ci_high": high,
            "mean_return": float(returns.mean()), "return_ci_low": return_low,
            "return_ci_high": return_high, "episodes": episodes}  # fmt: skip


@torch.no_grad()
def model_accuracy(
    model: WorldModel, encoder, task: str, hand_switch_prob: float = 0.0
) -> dict[str, float]:
    """M's accuracy from each macrostate's reference latent, read back by the encoder's
    classifier (docs/design.md section 3):

    - ``transition``: over all 192 x 6 true transitions, how often M's most likely next state
      shows the right macrostate. Terminal states never start a real transition, so 828
      (original) or 756 (hard) of the 1152 are never trained on: this includes generalization
      (the paper's Fig. 7 test).
    - ``transition_nonterminal``: the same over the 324 (original) or 396 (hard) transitions
      from non-terminal states, the ones M learns from.
    - ``transition_terminal``: the same over the transitions from terminal states, which no
      real transition starts from: M's generalization (the paper's Fig. 7 test, over all of
      them).
    - ``transition_sampled``: as ``transition_nonterminal`` but with a *sample* of M
      (component, then Gaussian; fixed seed): what imagination consumes. With a stochastic
      human (``hand_switch_prob`` > 0) a sample is right when it shows a possible next state
      (the arrows right, the hand anywhere); the most likely next state must keep the hand.
    - ``hand_kept_sampled`` (only with a stochastic human): of the samples with the arrows
      right, the share that keeps the hand, M's probability of a hand that stays (truth:
      1 - ``hand_switch_prob``).
    - ``reward`` / ``terminal``: over those same transitions, how often r (rounded to the nearest
      of +50, -5, -1) and d are right at the true next state's latent.

    With an ensemble of MDNs (``model_ensemble`` > 1) the most likely next state is the
    members' mean mode (:meth:`WorldModel.most_likely`); samples come from its first member.
    """
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    truth = apply_actions(states, actions)
    latents = encoder.state_latents()
    z = latents.repeat_interleave(N_ACTIONS, dim=0)
    was_training = model.training
    model.eval()
    next_z = model.most_likely(z, torch.as_tensor(actions))
    right_state = (encoder.classify(next_z).numpy() == truth).all(-1)
    seen = ~is_terminal(states, task)
    generator = torch.Generator().manual_seed(0)
    sampled = encoder.classify(
        model.mdn.sample(z[seen], torch.as_tensor(actions[seen]), generator)
    ).numpy()
    arrows_right = (sampled[:, :3] == truth[seen][:, :3]).all(-1)
    hand_kept = sampled[:, 3] == truth[seen][:, 3]
    right_sample = arrows_right if hand_switch_prob > 0 else arrows_right & hand_kept
    true_next = latents[torch.as_tensor(macrostate_index(truth[seen]))]
    levels = torch.tensor([REWARD_GOAL, REWARD_ILLEGAL, REWARD_STEP])
    reward = levels[(model.reward(true_next)[:, None] - levels).abs().argmin(-1)].numpy()
    terminal = model.terminal.is_terminal(true_next).numpy()
    model.train(was_training)
    out = {
        "transition": float(right_state.mean()),
        "transition_nonterminal": float(right_state[seen].mean()),
        "transition_terminal": float(right_state[~seen].mean()),
        "transition_sampled": float(right_sample.mean()),
        "reward": float((reward == rewards(truth[seen], task)).mean()),
        "terminal": float((terminal == is_terminal(truth[seen], task)).mean()),
    }
    if hand_switch_prob > 0:
        out["hand_kept_sampled"] = (
            float(hand_kept[arrows_right].mean()) if arrows_right.any() else 0.0
        )
    return out


@torch.no_grad()
def hand_calibration(
    model: WorldModel, encoder, task: str, p: float, include_terminal: bool = False
) -> dict[str, float | int]:
    """How M's mixture divides its probability among the hand's outcomes (issue 16), over
    every transition from a non-terminal state (the ones M learns from; ``include_terminal``:
    all 192 x 6, those from terminal states being generalization): each component's weight
    goes to the outcome its mean shows (read back by the encoder's classifier): the hand kept
    (truth 1 - p), moved to one of the other two cubes (truth p / 2 each, ``moved_*``: the cube
    after the pointed one, then the one before), or a wrong state (arrows wrong).
    ``total_variation``: the mean over transitions of half the summed absolute differences
    from the truth (0: calibrated); ``transitions``: how many were judged."""
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    if not include_terminal:
        seen = ~is_terminal(states, task)
        states, actions = states[seen], actions[seen]
    mass = hand_outcome_weights(model, encoder, states, actions)
    return {
        "p": p,
        "kept": float(mass[:, 0].mean()),
        "moved_next": float(mass[:, 1].mean()),
        "moved_previous": float(mass[:, 2].mean()),
        "wrong": float(mass[:, 3].mean()),
        "total_variation": float(hand_total_variation(mass, p).mean()),
        "transitions": len(states),
    }


@torch.no_grad()
def hand_outcome_weights(
    model: WorldModel, encoder, states: np.ndarray, actions: np.ndarray
) -> np.ndarray:
    """M's mixture weight on each outcome of each (state, action) (n, 4): the hand kept, moved
    to the cube after the pointed one, to the one before, or a wrong state (arrows wrong), each
    component's weight going to what its mean shows (read back by the encoder's classifier)."""
    truth = apply_actions(states, actions)
    z = encoder.state_latents()[torch.as_tensor(macrostate_index(states))]
    was_training = model.training
    model.eval()
    mixture = model.mdn(z, torch.as_tensor(actions))
    model.train(was_training)
    n, k, d = mixture.mu.shape
    shown = encoder.classify(mixture.mu.reshape(n * k, d)).numpy().reshape(n, k, 4)
    return outcome_mass(truth, shown, mixture.log_pi.exp().numpy())


def outcome_mass(truth: np.ndarray, shown: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The weight (n, 4) on the hand kept, moved +1, moved +2 and a wrong state of ``weight``
    (n, k) spread over next macrostates ``shown`` (n, k, 4), against the true rotated states
    ``truth`` (n, 4) (hand kept)."""
    arrows = (shown[..., :3] == truth[:, None, :3]).all(-1)
    hand = truth[:, None, 3]
    outcomes = [arrows & (shown[..., 3] == (hand + shift) % 3) for shift in (0, 1, 2)]
    mass = np.stack([(weight * o).sum(-1) for o in outcomes], -1)  # (n, 3): kept, +1, +2
    return np.concatenate([mass, 1.0 - mass.sum(-1, keepdims=True)], -1)


def hand_total_variation(mass: np.ndarray, p: float) -> np.ndarray:
    """Each row's total variation (n,) from the stochastic human's truth (1 - p, p / 2, p / 2,
    0): half the summed absolute differences."""
    return 0.5 * np.abs(mass - np.array([1.0 - p, p / 2, p / 2, 0.0])).sum(-1)


def random_success(
    task: str, episodes: int, seed: int, hand_switch_prob: float = 0.0
) -> dict[str, float]:
    """The random agent of Tables I and II: uniform actions in ``episodes`` test episodes."""
    envs = GesturePuzzleVectorEnv(episodes, task=task, autoreset_mode=AutoresetMode.SAME_STEP,
                                  hand_switch_prob=hand_switch_prob)  # fmt: skip
    envs.reset(seed=seed)
    rng = np.random.default_rng(seed)
    running = np.ones(episodes, dtype=bool)
    success = np.zeros(episodes, dtype=bool)
    while running.any():
        _, reward, terminated, truncated, _ = envs.step(rng.integers(0, N_ACTIONS, episodes))
        success |= running & (reward == REWARD_GOAL)
        running &= ~(terminated | truncated)
    n = int(success.sum())
    low, high = wilson_interval(n, episodes)
    return {"success": n / episodes, "ci_low": low, "ci_high": high, "episodes": episodes}


@torch.no_grad()
def imagined_accuracy(
    agent, starts: int = 100, seed: int = 0, model=None, draw: str | None = None
) -> dict[str, float]:
    """How right the transitions are that imagination hands C. From ``starts`` real start
    states (first images of new episodes, or states of its M_R for an agent that imagines from
    there: :func:`imagined_transitions`), the agent's I_B rollouts of up to I_D steps,
    as Algorithm 1 imagines them (its start, draw and epsilon settings; the real epsilon taken
    at its floor). Each imagined transition (z, a, z', r, d) is judged by V's latent
    classifier, which the agent never uses: ``state`` when the macrostate read from z' is the
    true successor of the one read from z under a; ``reward`` and ``terminal`` when r and d
    are those of that true successor (r rounded to the nearest of the task's rewards;
    ``reward_error``: the mean absolute difference of r itself, what C learns from);
    ``first_step``: ``state`` on first steps only;
    ``transitions``: how many were judged. ``model``: a population-form M to judge instead of
    the agent's; ``draw``: ``sample`` or ``mode`` in place of the agent's ``imagination_draw``
    (the same M judged both ways).

    With an ensemble of K > 1 MDNs, the members' disagreement as a detector of wrong imagined
    states (:func:`disagreement_detection`): ``disagreement_auroc``, ``disagreement_mean``,
    ``state_agreed_half`` and ``state_disagreed_half``. With the agent's M_R in its checkpoint,
    ``support_auroc``: the same for the support distance
    (:func:`imagine.learning.gate.support_distance`). With either, the agent's gate
    (``imagination_gate``; ``mask`` for an agent without one, on its ``imagination_uncertainty``)
    applied to these transitions, its threshold set by the first steps of these same rollouts,
    which stand in for the agent's recent ones: ``accepted`` (the share kept), ``state_accepted``
    and ``state_rejected`` (``state`` over the kept and the dropped; NaN for none) and
    ``gate_threshold``."""
    c = agent.config
    generator = torch.Generator().manual_seed(seed)
    rollout, truth, right = imagined_transitions(agent, starts, generator, model, draw)
    levels = np.array([REWARD_GOAL, REWARD_ILLEGAL, REWARD_STEP])
    reward = levels[np.abs(rollout["reward"].numpy()[:, None] - levels).argmin(-1)]
    done = rollout["done"].numpy().astype(bool)
    judged = {
        "state": right,
        "first_step": right[: starts * c.imagination_breadth],  # time-major: first steps
        "reward": reward == rewards(truth, c.task),
        "terminal": done == is_terminal(truth, c.task),
    }
    out = {key: float(values.mean()) for key, values in judged.items()}
    out["reward_error"] = float(np.abs(rollout["reward"].numpy() - rewards(truth, c.task)).mean())
    out["transitions"] = float(len(right))
    if c.model_ensemble > 1:
        out |= disagreement_detection(rollout["disagreement"].numpy(), right)
    uncertainty = rollout["disagreement"]  # what the agent's gate judges
    if agent.memory_starts is not None:
        support = support_distance(rollout["z"], rollout["action"], *agent.memory_starts)
        out["support_auroc"] = auroc(support.numpy(), ~right)
        if c.imagination_uncertainty == "support":
            uncertainty = support
    gated_by_support = c.imagination_uncertainty == "support" and "support_auroc" in out
    if c.model_ensemble > 1 or gated_by_support:
        out |= gate_judgement(agent.config, rollout, uncertainty, right, generator)
    return out


@torch.no_grad()
def imagined_transitions(
    agent, starts: int, generator: torch.Generator, model=None, draw: str | None = None
) -> tuple[dict[str, torch.Tensor], np.ndarray, np.ndarray]:
    """The transitions imagination hands C from ``starts`` real start states, as
    :func:`imagined_accuracy` describes them; with the true successor macrostate of each
    (V's classifier reading z, the rules applying a) and whether z' shows it. The start
    states are first images of new episodes (the env seeded by the generator's initial seed),
    or, for an agent that imagines from M_R (``imagination_from: memory``) with its M_R in
    the checkpoint, the mu of states drawn uniformly from M_R (its sigma is not saved: the
    rollouts start from mu, and the unit of the members' disagreement is V's posterior scale
    on the first images, as in training it is V's on M_R's states)."""
    c = agent.config
    envs = GesturePuzzleVectorEnv(starts, task=c.task, autoreset_mode=AutoresetMode.SAME_STEP,
                                  hand_switch_prob=c.hand_switch_prob)  # fmt: skip
    obs, info = envs.reset(seed=generator.initial_seed())  # draws nothing from the generator
    mu, sigma = agent.encoder.encode(obs, info["macrostate"])
    unit = posterior_scale(sigma)
    if c.imagination_from == "memory" and agent.memory_starts is not None:
        held = agent.memory_starts[0]
        mu = held[torch.randint(len(held), (starts,), generator=generator)]
        sigma = torch.zeros_like(mu)
        unit = unit.mean().expand(starts)
    breadth = c.imagination_breadth
    scale = unit.repeat_interleave(breadth).unsqueeze(0)
    if c.model_latents == "mu":
        sigma = torch.zeros_like(sigma)
    if model is None:
        model = PopulationWorldModel([agent.model]).eval()
    controller = PopulationController([agent.controller]).eval()
    eps = c.imagination_epsilon if c.imagination_epsilon >= 0 else c.eps_min
    rollout = imagine_rollouts(
        model, controller, mu.repeat_interleave(breadth, 0).unsqueeze(0),
        sigma.repeat_interleave(breadth, 0).unsqueeze(0), breadth, c.imagination_depth, [eps],
        [generator], draw=draw or c.imagination_draw, scale=scale,
        actions=actions_at(c, agent.episode),
    )[0]  # fmt: skip
    state = agent.encoder.classify(rollout["z"]).numpy()
    truth = apply_actions(state, rollout["action"].numpy())
    judged = slice(0, 3) if c.hand_switch_prob > 0 else slice(0, 4)  # a moved hand is possible
    shown = agent.encoder.classify(rollout["next_z"]).numpy()
    right = (shown[..., judged] == truth[..., judged]).all(-1)
    return rollout, truth, right


def gate_judgement(
    config,
    rollout: dict[str, torch.Tensor],
    disagreement: torch.Tensor,
    right: np.ndarray,
    generator: torch.Generator,
) -> dict[str, float]:
    """What the gate of ``config`` (``mask`` for ``none``) keeps of one agent's imagined
    transitions ``rollout``, judged by their uncertainty ``disagreement``, and how right
    (``right``, per transition) the kept and the dropped are; the threshold from these
    rollouts' first steps."""
    rule = "mask" if config.imagination_gate == "none" else config.imagination_gate
    threshold = gate_threshold(disagreement[rollout["step"] == 0],
                               config.imagination_gate_quantile,
                               config.imagination_gate_scale)  # fmt: skip
    keep = gate_transitions(rule, disagreement, rollout["rollout"], rollout["step"], threshold,
                            generator).numpy()  # fmt: skip
    return {
        "accepted": float(keep.mean()),
        "state_accepted": float(right[keep].mean()) if keep.any() else float("nan"),
        "state_rejected": float(right[~keep].mean()) if (~keep).any() else float("nan"),
        "gate_threshold": float(threshold),
    }


def auroc(scores: np.ndarray, positive: np.ndarray) -> float:
    """The area under the ROC curve of ``scores`` as a detector of ``positive``: the chance
    that a random positive scores above a random negative (ties count one half), from the
    ranks (the Mann-Whitney U statistic over n_pos * n_neg). NaN without both classes."""
    positive = np.asarray(positive, dtype=bool)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(scores)  # ties get their mean rank
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def disagreement_detection(disagreement: np.ndarray, right: np.ndarray) -> dict[str, float]:
    """How well the members' disagreement, which needs no labels, tells wrong imagined states
    (judged by V's classifier) from right ones: ``disagreement_auroc`` (1: every wrong one
    above every right one; 0.5: no better than chance), ``disagreement_mean``, and the state
    accuracy of the half of the transitions the members agree on most
    (``state_agreed_half``) and of the rest (``state_disagreed_half``)."""
    order = np.argsort(disagreement, kind="stable")
    agreed, rest = order[: len(order) // 2], order[len(order) // 2 :]
    return {
        "disagreement_auroc": auroc(disagreement, ~right),
        "disagreement_mean": float(disagreement.mean()),
        "state_agreed_half": float(right[agreed].mean()) if len(agreed) else float("nan"),
        "state_disagreed_half": float(right[rest].mean()) if len(rest) else float("nan"),
    }
