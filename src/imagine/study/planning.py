"""Generating plans with M and C (paper section V, Generating Plans; Fig. 5).

From the first observation alone: encode it, then roll M forward with C's greedy action and M's
most likely next state until the d-network says terminal (at most ``I_D`` = 10 steps). The
actions are the plan; it is executed open-loop in the real task and judged against the fewest
actions that solve it (breadth-first search on the true state machine). Paper: 17 of 20 plans
succeeded on the robot, every success optimal.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from imagine.checkpoint import save_figure
from imagine.envs.gesture_puzzle.rules import (
    apply_actions,
    is_goal,
    is_illegal,
    optimal_plan_length,
    start_states,
)


@dataclass(frozen=True)
class PlanResult:
    """How a plan did when executed open-loop from ``start``."""

    start: tuple[int, ...]
    actions: tuple[int, ...]
    success: bool
    """The plan reached a goal state without passing an illegal one."""
    steps: int
    """Actions executed (the real task stops at the first terminal state)."""
    optimal_length: int | None
    optimal: bool
    """Succeeded in the fewest possible actions."""


def judge_plan(start: np.ndarray, actions: list[int], task: str) -> PlanResult:
    """Execute ``actions`` open-loop from ``start`` on the true task and judge the plan."""
    state = np.asarray(start, dtype=np.int64)
    success, steps = False, 0
    for action in actions:
        state = apply_actions(state, np.asarray(action))
        steps += 1
        if is_illegal(state[None])[0]:
            break
        if is_goal(state[None], task)[0]:
            success = True
            break
    best = optimal_plan_length(tuple(int(x) for x in start), task)
    return PlanResult(
        start=tuple(int(x) for x in start), actions=tuple(int(a) for a in actions),
        success=success, steps=steps, optimal_length=best,
        optimal=success and steps == len(actions) and steps == best,
    )  # fmt: skip


@torch.no_grad()
def imagine_plan(agent, mu: torch.Tensor, depth: int = 10) -> tuple[list[int], torch.Tensor]:
    """C's greedy actions through M's most likely states from the latent ``mu`` (latent_dim,),
    until d says terminal or ``depth`` actions; returns the actions and the latents visited
    (start included), (len + 1, latent_dim). M and C are left in the modes they were in."""
    model, controller = agent.model, agent.controller
    modes = model.training, controller.training
    model.eval()
    controller.eval()
    mu = mu.to(next(model.parameters()).device)  # V may sit on a GPU, M and C on the CPU
    z, actions, latents = mu[None], [], [mu]
    for _ in range(depth):
        action = controller(z).argmax(-1)
        z = model.most_likely(z, action)
        actions.append(int(action))
        latents.append(z[0])
        if bool(model.terminal.is_terminal(z)[0]):
            break
    model.train(modes[0])
    controller.train(modes[1])
    return actions, torch.stack(latents)


def plan_trials(agent, trials: int = 20, seed: int = 0, depth: int = 10) -> list[PlanResult]:
    """``trials`` plans from random start states, each from one rendered observation."""
    from imagine.envs.gesture_puzzle import make_composer

    rng = np.random.default_rng(seed)
    starts = start_states(agent.config.task)
    chosen = starts[rng.integers(0, len(starts), trials)]
    images = make_composer().sample(rng, chosen)
    mu, _ = agent.encoder.encode(images, chosen)
    return [
        judge_plan(state, imagine_plan(agent, mu[i], depth)[0], agent.config.task)
        for i, state in enumerate(chosen)
    ]


def summarize_plans(results: list[PlanResult]) -> dict[str, Any]:
    successes = [r for r in results if r.success]
    return {
        "trials": len(results),
        "successes": len(successes),
        "optimal": sum(r.optimal for r in results),
        "success_lengths": [r.steps for r in successes],
        "optimal_lengths_of_successes": [r.optimal_length for r in successes],
        "plans": [asdict(r) for r in results],
    }


def rollout_png(agent, out: Path, length: int = 5, seed: int = 0, tries: int = 50) -> Path | None:
    """Paper Fig. 5: the first observation and V's decoding of each imagined latent of a plan,
    for a start state whose optimal plan has ``length`` actions (a successful plan of that
    length if one of ``tries`` starts gives it). None for the oracle encoder (nothing to
    decode)."""
    from matplotlib.figure import Figure

    from imagine.envs.gesture_puzzle import make_composer
    from imagine.envs.gesture_puzzle.rules import describe
    from imagine.envs.gesture_puzzle.vision_report import as_scene

    vae = getattr(agent.encoder, "vae", None)
    if vae is None:
        return None
    task = agent.config.task
    rng = np.random.default_rng(seed)
    candidates = [s for s in start_states(task) if optimal_plan_length(tuple(s), task) == length]
    if not candidates:
        return None
    composer = make_composer()
    best = None
    for _ in range(tries):
        state = candidates[rng.integers(len(candidates))]
        image = composer.sample(rng, state[None])
        mu, _ = agent.encoder.encode(image, state[None])
        actions, latents = imagine_plan(agent, mu[0])
        result = judge_plan(state, actions, task)
        best = best or (image[0], actions, latents, result)
        if result.optimal:
            best = (image[0], actions, latents, result)
            break
    image, actions, latents, result = best
    with torch.no_grad():
        decoded = vae.decode(latents[1:].to(next(vae.parameters()).device)).clamp(0, 1)
    decoded = decoded.cpu().numpy()
    panels = [as_scene(image)] + [as_scene(x) for x in decoded]
    fig = Figure(figsize=(2.2 * len(panels), 1.6), layout="constrained")
    states = [np.asarray(result.start)]
    for a in actions:
        states.append(apply_actions(states[-1], np.asarray(a)))
    for i, panel in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        ax.imshow(panel, cmap="gray", vmin=0, vmax=1)
        title = "observed" if i == 0 else f"imagined {i}: action {actions[i - 1]}"
        ax.set_title(f"{title}\n{describe(states[i])}", fontsize=7)
        ax.axis("off")
    verdict = "optimal" if result.optimal else ("succeeded" if result.success else "failed")
    fig.suptitle(f"plan of {len(actions)} actions from one observation ({verdict}; "
                 f"optimal {result.optimal_length})", fontsize=9)  # fmt: skip
    return save_figure(fig, out)
