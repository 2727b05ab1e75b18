"""How often can a *draw* of M be right with this V, however well M is trained?

M's targets are V's means of fresh images of the next state, so even a perfect M's component
for a macrostate is the cloud of those means, and its draw lands where a Gaussian of that
cloud puts it. This script renders ``--images`` images of each of the 192 macrostates, encodes
them with V, fits per macrostate the Gaussian that such an M would predict (diagonal, as M's
components are, and full covariance for comparison), draws from it, and reads the draws back
with V's latent classifier, as ``imagine evaluate``'s sampled accuracy does. Rows are weighted
as that accuracy is: over the next states of each task's non-terminal transitions.

    .venv/bin/python scripts/m_sample_bound.py runs/vae-fast [--images 64]

`imagine vae report` prints the diagonal rows for any V (`vision_report.draw_accuracy`);
this script adds the full-covariance Gaussian and the per-task weighting.

A bound for M's form, not for M: an M whose scales are narrower than the cloud's does better
on draws, and one whose scales are wider (dropout, too little training) worse. M's mixture has
``n_components`` (5) diagonal components per transition, so it may also spread them over one
outcome's cloud: the rows "K-component diagonal mixture" fit K components to each
macrostate's cloud by expectation-maximization
(:func:`imagine.envs.gesture_puzzle.vision_report.diagonal_mixture`, a local maximum of the
likelihood): what an M of that form fitted to each cloud would draw.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.encoders import VaeEncoder
from imagine.envs.gesture_puzzle.rules import (
    N_ACTIONS,
    all_macrostates,
    apply_actions,
    is_terminal,
    macrostate_index,
)
from imagine.envs.gesture_puzzle.vision_report import diagonal_mixture, mixture_draws


def next_state_weights(task: str) -> np.ndarray:
    """How often each macrostate is the next state of a non-terminal transition of ``task``."""
    states = np.repeat(all_macrostates(), N_ACTIONS, axis=0)
    actions = np.tile(np.arange(N_ACTIONS), len(all_macrostates()))
    seen = ~is_terminal(states, task)
    index = macrostate_index(apply_actions(states[seen], actions[seen]))
    return np.bincount(index, minlength=192) / len(index)


def right(encoder: VaeEncoder, draws: torch.Tensor) -> np.ndarray:
    """(192, n) draws' latents -> per macrostate, the share read back as that macrostate."""
    n = draws.shape[1]
    truth = np.repeat(all_macrostates(), n, axis=0)
    read = encoder.classify(draws.reshape(192 * n, -1)).numpy()
    return (read == truth).all(-1).reshape(192, n).mean(1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("vae")
    parser.add_argument("--images", type=int, default=64)
    args = parser.parse_args()
    torch.set_num_threads(1)
    composer = make_composer()
    encoder = VaeEncoder(args.vae, composer)
    rng = np.random.default_rng(1)
    n = args.images
    states = np.repeat(all_macrostates(), 2 * n, axis=0)
    mu, sigma = encoder.encode(composer.sample(rng, states), states)
    clouds = mu.view(192, 2 * n, -1)
    fit, held_out = clouds[:, :n], clouds[:, n:]  # fit on half, the other half is V itself
    mean, std = fit.mean(1, keepdim=True), fit.std(1, keepdim=True)
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(held_out.shape, generator=generator)
    rows = {"V's own means of fresh images (the classifier's accuracy)": right(encoder, held_out)}
    for tau in (1.0, 0.5, 0.25):
        rows[f"diagonal Gaussian fit to V's cloud, scales x {tau}"] = right(
            encoder, mean + tau * std * noise
        )
    centred = fit - mean
    cov = centred.transpose(1, 2) @ centred / (n - 1)
    chol = torch.linalg.cholesky(cov + 1e-6 * torch.eye(cov.shape[-1]))
    rows["full-covariance Gaussian fit to V's cloud"] = right(
        encoder, mean + (chol @ noise.transpose(1, 2)).transpose(1, 2)
    )
    for k in (2, 3, 5):
        rows[f"{k}-component diagonal mixture fit to V's cloud (EM)"] = right(
            encoder, mixture_draws(*diagonal_mixture(fit, k), n, generator)
        )
    posterior = sigma.view(192, 2 * n, -1)[:, n:]
    rows["V's posterior draw N(mu, sigma) of fresh images"] = right(
        encoder, held_out + posterior * torch.randn(held_out.shape, generator=generator)
    )
    weights = {task: next_state_weights(task) for task in ("original", "hard")}
    print(f"V: {args.vae}; {n} images per macrostate to fit, {n} to draw and test")
    print("| draw | all 192 macrostates | original, non-terminal | hard, non-terminal |")
    print("| --- | --- | --- | --- |")
    for name, share in rows.items():
        cells = [f"{100 * share.mean():.1f}"]
        cells += [f"{100 * float(weights[t] @ share):.1f}" for t in ("original", "hard")]
        print(f"| {name} | " + " | ".join(cells) + " |")
    spread = std.squeeze(1).mean(0)
    print("mean within-macrostate std of V's means, per dimension: "
          + ", ".join(f"{x:.3f}" for x in spread.tolist()))  # fmt: skip


if __name__ == "__main__":
    main()
