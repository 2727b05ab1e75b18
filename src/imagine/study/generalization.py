"""Model generalization (paper section V, Model Generalization; Fig. 7).

Terminal states end an episode, so no real transition ever starts from one: M never trains on
them. Put M in such a state (from a fresh rendered observation), apply an action, and check
whether its most likely next state shows the right macrostate (read by the latent classifier).
The paper: 75% of 20 trials right after 5000 episodes. We report its 20-trial test and the
same over every terminal state and action.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from imagine.checkpoint import save_figure
from imagine.envs.gesture_puzzle.rules import N_ACTIONS, all_macrostates, apply_actions, is_terminal


@torch.no_grad()
def predict_next(agent, images: np.ndarray, states: np.ndarray, actions: np.ndarray):
    """M's most likely next latent from each observation under each action, and the
    macrostate the classifier reads from it."""
    mu, _ = agent.encoder.encode(images, states)
    next_z = next_from(agent, mu, actions)
    return next_z, agent.encoder.classify(next_z).numpy()


@torch.no_grad()
def next_from(agent, mu: torch.Tensor, actions: np.ndarray, first_member: bool = False):
    """M's most likely next latent from V's means (:meth:`WorldModel.most_likely`; with
    ``first_member``, an ensemble's first MDN alone), without dropout; M is left in the mode
    it was in."""
    device = next(agent.model.parameters()).device  # V may sit on a GPU, M on the CPU
    model = agent.model
    was_training = model.training
    model.eval()
    predict = model.mdn.most_likely if first_member else model.most_likely
    next_z = predict(mu.to(device), torch.as_tensor(actions, device=device))
    model.train(was_training)
    return next_z


def generalization(agent, trials: int = 20, seed: int = 0) -> dict[str, Any]:
    """Accuracy of M's next state from terminal states: ``trials`` random (state, action)
    pairs as the paper, and all terminal states x 6 actions (with an ensemble, of the
    members' mean mode, and of its first member alone as well)."""
    from imagine.envs.gesture_puzzle import make_composer

    task = agent.config.task
    rng = np.random.default_rng(seed)
    terminal = all_macrostates()[is_terminal(all_macrostates(), task)]
    composer = make_composer()
    picked = terminal[rng.integers(0, len(terminal), trials)]
    actions = rng.integers(0, N_ACTIONS, trials)
    _, read = predict_next(agent, composer.sample(rng, picked), picked, actions)
    right = (read == apply_actions(picked, actions)).all(-1)
    every = np.repeat(terminal, N_ACTIONS, axis=0)
    every_actions = np.tile(np.arange(N_ACTIONS), len(terminal))
    mu_all, _ = agent.encoder.encode(composer.sample(rng, every), every)
    truth_all = apply_actions(every, every_actions)
    read_all = agent.encoder.classify(next_from(agent, mu_all, every_actions)).numpy()
    right_all = (read_all == truth_all).all(-1)
    result = {
        "trials": trials,
        "trials_right": int(right.sum()),
        "trial_accuracy": float(right.mean()),
        "all_terminal_transitions": len(every),
        "all_terminal_accuracy": float(right_all.mean()),
    }
    if len(agent.model.members) > 1:  # the ensemble's mean mode above; its first member alone
        first = next_from(agent, mu_all, every_actions, first_member=True)
        result["all_terminal_accuracy_first_member"] = float(
            (agent.encoder.classify(first).numpy() == truth_all).all(-1).mean()
        )
    return result


def generalization_png(agent, out: Path, seed: int = 0) -> Path | None:
    """Paper Fig. 7: an observed terminal state, the action, V's decoding of M's prediction and
    an observation of the true next state. None for the oracle encoder."""
    from matplotlib.figure import Figure

    from imagine.envs.gesture_puzzle import make_composer
    from imagine.envs.gesture_puzzle.rules import describe
    from imagine.envs.gesture_puzzle.vision_report import as_scene

    vae = getattr(agent.encoder, "vae", None)
    if vae is None:
        return None
    task = agent.config.task
    rng = np.random.default_rng(seed)
    terminal = all_macrostates()[is_terminal(all_macrostates(), task)]
    composer = make_composer()
    state = terminal[rng.integers(len(terminal))][None]
    action = rng.integers(0, N_ACTIONS, 1)
    truth = apply_actions(state, action)
    image = composer.sample(rng, state)
    next_z, read = predict_next(agent, image, state, action)
    with torch.no_grad():
        decoded = vae.decode(next_z.to(next(vae.parameters()).device)).clamp(0, 1)[0].cpu()
    panels = [
        (as_scene(image[0]), f"terminal state (observed)\n{describe(state[0])}"),
        (as_scene(decoded), f"M's prediction, action {int(action[0])}\nreads {describe(read[0])}"),
        (as_scene(composer.sample(rng, truth)[0]), f"true next state\n{describe(truth[0])}"),
    ]
    fig = Figure(figsize=(7.5, 1.8), layout="constrained")
    for i, (panel, title) in enumerate(panels):
        ax = fig.add_subplot(1, 3, i + 1)
        ax.imshow(panel, cmap="gray", vmin=0, vmax=1)
        ax.set_title(title, fontsize=7)
        ax.axis("off")
    verdict = "right" if (read == truth).all() else "wrong"
    fig.suptitle(f"M from a state it never trained on: prediction {verdict}", fontsize=9)
    return save_figure(fig, out)
