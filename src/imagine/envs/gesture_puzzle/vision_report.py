"""`imagine vae report`: how good V is, in numbers and pictures.

Writes ``reconstructions.png`` (test images beside their reconstructions, each observation shown
as its three strips side by side, as the scene), ``traversals.png`` (one row per latent
dimension, that dimension swept from -3 to +3 around a test image's mean) and ``report.json``
with the test reconstruction loss and KL per image and the latent classifier's accuracy on fresh
test images (a seed V never saw), per cube arrow and for the hand, and how often a draw of an
M fitted to V's clouds, with one diagonal Gaussian or with as many diagonal components as M
has, lands on the right macrostate in this V's latent space (:func:`draw_accuracy`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from matplotlib.figure import Figure

from imagine.checkpoint import save_figure, write_json
from imagine.config import VisionConfig
from imagine.envs.gesture_puzzle.dataset import DatasetConfig, synthesize
from imagine.envs.gesture_puzzle.latent_classifier import LatentClassifier
from imagine.models.vision import ACTIVE_VARIANCE, ConvVAE, encode_images, to_input


def as_scene(x: torch.Tensor | np.ndarray) -> np.ndarray:
    """An observation, (3, 64, 64) in [0, 1] or uint8 (64, 64, 3), as its strips side by side."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    if x.shape[0] == 3:
        x = np.moveaxis(x, 0, -1)
    x = x.astype(np.float64) / (255.0 if x.dtype == np.uint8 or x.max() > 1.5 else 1.0)
    return np.concatenate([x[..., 0], x[..., 1], x[..., 2]], axis=1)


def reconstructions_png(vae: ConvVAE, images: np.ndarray, out: Path, n: int = 8) -> Path:
    n = min(n, len(images))
    with torch.no_grad():
        vae.eval()
        mu, _ = vae.encode(to_input(images[:n]))
        recon = vae.decode(mu)
    fig = Figure(figsize=(8, 1.0 * n), layout="constrained")
    axes = fig.subplots(n, 2, squeeze=False)
    for i in range(n):
        for j, (img, title) in enumerate(((images[i], "test image"), (recon[i], "reconstruction"))):
            axes[i, j].imshow(as_scene(img), cmap="gray", vmin=0, vmax=1)
            axes[i, j].axis("off")
            if i == 0:
                axes[i, j].set_title(title)
    save_figure(fig, out, dpi=80)
    return out


def traversals_png(vae: ConvVAE, image: np.ndarray, out: Path, steps: int = 7) -> Path:
    with torch.no_grad():
        vae.eval()
        mu, _ = vae.encode(to_input(image[None]))
        values = torch.linspace(-3, 3, steps)
        rows = []
        for dim in range(vae.latent_dim):
            z = mu.repeat(steps, 1)
            z[:, dim] = values
            rows.append(vae.decode(z))
    fig = Figure(figsize=(1.9 * steps, 0.75 * vae.latent_dim + 0.5), layout="constrained")
    axes = fig.subplots(vae.latent_dim, steps, squeeze=False)
    for dim, row in enumerate(rows):
        for k in range(steps):
            axes[dim, k].imshow(as_scene(row[k]), cmap="gray", vmin=0, vmax=1)
            axes[dim, k].set_xticks([])
            axes[dim, k].set_yticks([])
            if k == 0:
                axes[dim, k].set_ylabel(f"z{dim}")
            if dim == 0:
                axes[dim, k].set_title(f"{float(values[k]):+.1f}")
    fig.suptitle("latent traversals: each row sweeps one dimension of z around a test image")
    save_figure(fig, out, dpi=80)
    return out


def latent_activity(mu: torch.Tensor, sigma: torch.Tensor) -> dict[str, Any]:
    """Per latent dimension, over encoded images: the KL of the posterior from the prior
    (nats per image), the variance of the mean across images (activity), the mean posterior
    sigma; and which dimensions are collapsed (inactive)."""
    kl = (-0.5 * (1 + 2 * sigma.log() - mu.square() - sigma.square())).mean(0)
    activity = mu.var(0)
    collapsed = [d for d in range(mu.shape[1]) if float(activity[d]) <= ACTIVE_VARIANCE]
    return {
        "kl_per_dimension": [round(float(x), 4) for x in kl],
        "mean_variance_per_dimension": [round(float(x), 4) for x in activity],
        "sigma_per_dimension": [round(float(x), 4) for x in sigma.mean(0)],
        "collapsed_dimensions": collapsed,
        "active_dimensions": mu.shape[1] - len(collapsed),
    }


def macrostate_separation(mu: torch.Tensor, states: np.ndarray) -> dict[str, Any]:
    """How far apart V puts the macrostates against how much it moves within one (the images
    of one macrostate differ by their fragments, lighting and jitter: its microstates).

    Per dimension: the spread of the macrostates' mean latents (between) and the mean spread of
    the latents of one macrostate's images (within). Overall: the distance from each
    macrostate's mean latent to the nearest other one (min, median), against the mean distance
    of an image's latent from its own macrostate's mean. C and M read single images, so a ratio
    (median nearest / within) below 1 means a typical latent lies farther from its own
    macrostate's mean than that mean lies from its neighbour's: the microstate is as loud as
    the macrostate, and C must learn to ignore it."""
    from imagine.envs.gesture_puzzle.rules import macrostate_index

    index = torch.as_tensor(macrostate_index(states))
    seen = index.unique()
    means = torch.stack([mu[index == i].mean(0) for i in seen])
    within = torch.stack([mu[index == i].std(0) for i in seen if int((index == i).sum()) > 1])
    offsets = mu - means[torch.searchsorted(seen, index)]
    gaps = torch.cdist(means, means).fill_diagonal_(float("inf")).min(1).values
    nearest, spread = float(gaps.median()), float(offsets.norm(dim=-1).mean())
    return {
        "between_std_per_dimension": [round(float(x), 4) for x in means.std(0)],
        "within_std_per_dimension": [round(float(x), 4) for x in within.mean(0)],
        "nearest_macrostate_distance_min": round(float(gaps.min()), 4),
        "nearest_macrostate_distance_median": round(nearest, 4),
        "within_macrostate_distance": round(spread, 4),
        "separation_ratio": round(nearest / spread, 4),
    }


DRAW_SCALES = (1.0, 0.5)
"""Scales of the fitted Gaussians' standard deviations in :func:`draw_accuracy`."""

DRAW_COMPONENTS = 5
"""Components of the diagonal mixture fitted to each cloud in :func:`draw_accuracy`: M's
``n_components``."""


def diagonal_mixture(
    x: torch.Tensor, k: int, iterations: int = 200, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per group of points x (G, N, D) a k-component diagonal Gaussian mixture fitted by
    expectation-maximization (a local maximum of the likelihood; means started at k distinct
    points of the group): weights (G, k), means (G, k, D), variances (G, k, D)."""
    groups, n, d = x.shape
    generator = torch.Generator().manual_seed(seed)
    start = torch.stack([torch.randperm(n, generator=generator)[:k] for _ in range(groups)])
    mean = x.gather(1, start[..., None].expand(groups, k, d)).clone()
    var = x.var(1, keepdim=True).expand(groups, k, d).clone()
    weight = torch.full((groups, k), 1.0 / k)
    for _ in range(iterations):
        log_p = -0.5 * ((x[:, :, None] - mean[:, None]).square() / var[:, None]
                        + var[:, None].log()).sum(-1) + weight.log()[:, None]  # fmt: skip
        resp = torch.softmax(log_p, -1)  # (G, N, k): E step
        mass = resp.sum(1) + 1e-8  # M step
        weight = mass / n
        mean = resp.transpose(1, 2) @ x / mass[..., None]
        var = (resp.transpose(1, 2) @ x.square() / mass[..., None] - mean.square()).clamp(min=1e-5)
    return weight, mean, var


def mixture_draws(
    weight: torch.Tensor,
    mean: torch.Tensor,
    var: torch.Tensor,
    n: int,
    generator: torch.Generator,
) -> torch.Tensor:
    """n draws (G, n, D) from each group's diagonal mixture: a component by weight, then its
    Gaussian."""
    groups, _, d = mean.shape
    k = torch.multinomial(weight, n, replacement=True, generator=generator)[..., None]
    k = k.expand(groups, n, d)
    noise = torch.randn(groups, n, d, generator=generator)
    return mean.gather(1, k) + var.gather(1, k).sqrt() * noise


def draw_accuracy(
    mu: torch.Tensor,
    states: np.ndarray,
    classify,
    scales: tuple[float, ...] = DRAW_SCALES,
    components: int = DRAW_COMPONENTS,
    seed: int = 0,
) -> dict[str, float]:
    """How often a draw of an M fitted to V's clouds lands on the right macrostate.

    M's targets are V's means of fresh images of the next state, so a perfect M's prediction
    for a macrostate is a density of that macrostate's cloud of means. Per macrostate, fit to
    ``mu`` one diagonal Gaussian (mean and standard deviation per dimension; ``scale_s``: its
    standard deviations times each of ``scales``, 1 a plain draw, below 1 a draw at a lower
    temperature) and a ``components``-component diagonal mixture (:func:`diagonal_mixture`;
    ``components_k``: M's form, whose components may share out one cloud; on clouds of at
    least 2k points, NaN without any), draw as many latents
    from each and read them back with ``classify`` ((N, d) latents to (N, k) macrostates): the
    share read as the right one. A cloud that is not axis-aligned (V's dimensions moving
    together from image to image) leaks into its neighbours under one diagonal Gaussian, which
    the most likely state never does and a mixture of several does less."""
    from imagine.envs.gesture_puzzle.rules import macrostate_index

    index = torch.as_tensor(macrostate_index(states))
    generator = torch.Generator().manual_seed(seed)
    mixing = torch.Generator().manual_seed(seed + 1)  # leaves the Gaussians' draws as they were
    mixed = f"components_{components}"
    draws: dict[str, list[torch.Tensor]] = {f"scale_{s:g}": [] for s in scales} | {mixed: []}
    truth: dict[str, list[np.ndarray]] = {key: [] for key in draws}
    for i in index.unique():
        cloud, shown = mu[index == i], states[(index == i).numpy()]
        if len(cloud) < 2:
            continue
        noise = torch.randn(cloud.shape, generator=generator)
        for scale in scales:
            draws[f"scale_{scale:g}"].append(cloud.mean(0) + scale * cloud.std(0) * noise)
            truth[f"scale_{scale:g}"].append(shown)
        if len(cloud) >= 2 * components:  # a mixture needs a few points per component
            mixture = diagonal_mixture(cloud[None], components, seed=seed)
            draws[mixed].append(mixture_draws(*mixture, len(cloud), mixing)[0])
            truth[mixed].append(shown)
    return {
        key: float((classify(torch.cat(z)).numpy() == np.concatenate(truth[key])).all(-1).mean())
        if z
        else float("nan")
        for key, z in draws.items()
    }


def linear_probe_accuracy(
    fit_mu: torch.Tensor, fit_states: np.ndarray, mu: torch.Tensor, states: np.ndarray
) -> dict[str, float]:
    """Accuracy on (mu, states) of a linear probe fitted on (fit_mu, fit_states): how much of
    the macrostate V lays out linearly, which is what a small M or C reads most easily."""
    probe = LatentClassifier(fit_mu.shape[1], hidden=0)
    probe.fit(fit_mu, torch.as_tensor(fit_states), steps=1500, lr=3e-2)
    return probe.accuracy(mu, torch.as_tensor(states))


def fresh_test_set(made: DatasetConfig) -> tuple[np.ndarray, np.ndarray]:
    """Images V never saw (see :func:`~imagine.models.vision_training.fresh_images_config`)."""
    arrays = synthesize(made)
    return arrays["train_images"], arrays["train_macrostates"]


def vision_report(
    vae: ConvVAE,
    classifier: LatentClassifier,
    config: VisionConfig,
    test_images: np.ndarray,
    test_loss: dict[str, float],
    folder: Path,
    fresh: DatasetConfig,
    fit: tuple[np.ndarray, np.ndarray],
) -> dict[str, Any]:
    """Write the PNGs and report.json into ``folder``; return the numbers. ``fit``: images and
    macrostates the linear probe is fitted on (V's training images)."""
    images, states = fresh_test_set(fresh)
    mu, sigma = encode_images(vae, images)
    accuracy = classifier.accuracy(mu, torch.as_tensor(states))
    fit_mu, _ = encode_images(vae, fit[0])
    report = {
        "test_reconstruction_per_image": test_loss["reconstruction"],
        "test_kl_per_image": test_loss["kl"],
        "test_loss_per_image": test_loss["loss"],
        "classifier_accuracy": accuracy,
        "linear_probe_accuracy": linear_probe_accuracy(fit_mu, fit[1], mu, states),
        "diagonal_draw_accuracy": draw_accuracy(mu, states, classifier.predict),
        "classifier_test_images": len(images),
        **latent_activity(mu, sigma),
        **macrostate_separation(mu, states),
    }
    reconstructions_png(vae, test_images, folder / "reconstructions.png")
    traversals_png(vae, test_images[0], folder / "traversals.png")
    write_json(folder / "report.json", report)
    return report


def report_run(run: Path) -> tuple[dict[str, Any], int]:
    """Write the PNGs and report.json of the V run folder ``run``; return the numbers and the
    epochs V has finished."""
    from imagine.models.vision_training import (
        evaluate_vae,
        fresh_images_config,
        load_classifier,
        load_vae,
        make_data,
    )

    vae, config, epoch = load_vae(run)
    classifier = load_classifier(run, config.latent_dim)
    data = make_data(config)
    test_loss = evaluate_vae(vae, data.test_images, config.beta, config.seed + 1)
    n = min(config.n_classifier_fit, len(data.train_images))
    fit = (data.train_images[:n], data.train_states[:n])
    report = vision_report(
        vae, classifier, config, data.test_images, test_loss, run, fresh_images_config(config),
        fit,
    )  # fmt: skip
    return report, epoch


def agent_model_accuracy(run: Path, agent_run: Path) -> dict[str, float]:
    """M's accuracy (:func:`~imagine.envs.gesture_puzzle.evaluation.model_accuracy`) of the agent
    in ``agent_run``, which must have been trained with the V in ``run``; added to ``run``'s
    report.json."""
    from imagine.checkpoint import read_json
    from imagine.envs.gesture_puzzle.evaluation import model_accuracy
    from imagine.errors import ConfigError
    from imagine.learning.agent import load_agent

    agent = load_agent(agent_run)
    if agent.config.vae_run is None or Path(agent.config.vae_run).resolve() != run.resolve():
        raise ConfigError(f"{agent_run} was not trained with the V in {run}")
    if not agent.config.trains_model:
        raise ConfigError(f"{agent_run} is a baseline run: it has no trained M")
    c = agent.config
    accuracy = model_accuracy(agent.model, agent.encoder, c.task, c.hand_switch_prob)
    report = read_json(run / "report.json", "V report")
    report["model_accuracy"] = {"agent": str(agent_run), **accuracy}
    write_json(run / "report.json", report)
    return accuracy
