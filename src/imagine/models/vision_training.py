"""Training V, resumable, with per-epoch metrics (paper section V-B).

A V run folder holds:

- ``config.yaml``: the resolved :class:`~imagine.config.VisionConfig`;
- ``vae.safetensors`` + ``vae.json``: the model, Adam's state and the random generator state
  after the last finished epoch, and the epoch count; written atomically every epoch, so a run
  stopped at any moment resumes from its last finished epoch with the same numbers;
- ``classifier.safetensors``: the latent classifier fitted when training ends;
- ``metrics.csv`` and ``tensorboard/``: per-epoch train and test loss, reconstruction and KL
  apart, per image.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from imagine.checkpoint import (
    atomic_write_text,
    changed_fields,
    load_state_dict_strict,
    load_tensors,
    optimizer_from_tensors,
    optimizer_to_tensors,
    read_json,
    save_tensors,
    write_json,
)
from imagine.config import VisionConfig, from_dict
from imagine.devices import resolve_device
from imagine.envs.gesture_puzzle.dataset import DatasetConfig, load_dataset, synthesize
from imagine.envs.gesture_puzzle.latent_classifier import LatentClassifier
from imagine.errors import CheckpointError, ConfigError
from imagine.metrics import MetricsLogger
from imagine.models.vision import ConvVAE, encode_images, to_input

FORMAT = "imagine-vae-1"


@dataclass
class VisionData:
    train_images: np.ndarray
    train_states: np.ndarray | None
    """GesturePuzzle's macrostates of the images (None for another environment's frames)."""
    test_images: np.ndarray
    test_states: np.ndarray | None


def make_data(config: VisionConfig) -> VisionData:
    """The training and test images of a config: its dataset file, another environment's
    frames, or synthesized (deterministically) from the procedural renderer."""
    if config.env is not None:
        from imagine.envs.spec import gym_spec
        from imagine.models.frames import random_frames

        spec = gym_spec(config.env, tuple(config.env_wrappers))
        if spec.kind != "image":
            raise ConfigError(f"{config.env} has {spec.kind} observations: V is for images")
        frames = random_frames(spec, config.n_train + config.n_test, config.data_seed)
        return VisionData(frames[: config.n_train], None, frames[config.n_train :], None)
    if config.dataset is not None:
        arrays, made = load_dataset(config.dataset)
        if (made.n_train, made.n_test) != (config.n_train, config.n_test):
            raise ConfigError(
                f"{config.dataset} holds {made.n_train} + {made.n_test} images but the config "
                f"says {config.n_train} + {config.n_test}; use with_dataset(config)"
            )
    else:
        arrays = synthesize(DatasetConfig(config.n_train, config.n_test, config.data_seed))
    return VisionData(
        arrays["train_images"], arrays["train_macrostates"],
        arrays["test_images"], arrays["test_macrostates"],
    )  # fmt: skip


def with_dataset(config: VisionConfig, path: str | Path) -> VisionConfig:
    """``config`` set to train on the dataset file at ``path`` (its sizes and seed)."""
    _, made = load_dataset(path)
    return dataclasses.replace(
        config, dataset=str(path), n_train=made.n_train, n_test=made.n_test, data_seed=made.seed,
        n_classifier_fit=min(config.n_classifier_fit, made.n_train),
    )  # fmt: skip


def fresh_images_config(config: VisionConfig) -> DatasetConfig:
    """Images V never saw, from the same fragments as its training images, another seed."""
    made = (
        DatasetConfig(config.n_train, config.n_test, config.data_seed)
        if config.dataset is None
        else load_dataset(config.dataset)[1]
    )
    return dataclasses.replace(made, n_train=config.n_classifier_test, n_test=1, seed=made.seed + 1)


def evaluate_vae(vae: ConvVAE, images: np.ndarray, beta: float, seed: int) -> dict[str, float]:
    """Mean test loss per image, with a fixed noise seed so epochs compare fairly."""
    device = next(vae.parameters()).device
    generator = torch.Generator(device).manual_seed(seed)
    vae.eval()
    totals = np.zeros(3)
    with torch.no_grad():
        for start in range(0, len(images), 1000):
            x = to_input(images[start : start + 1000]).to(device)
            x = x.contiguous(memory_format=torch.channels_last)
            loss = vae.loss(x, beta, generator)
            totals += len(x) * np.array([float(v) for v in loss])
    vae.train()
    total, reconstruction, kl = totals / len(images)
    return {"loss": total, "reconstruction": reconstruction, "kl": kl}


def save_vae(folder: Path, vae: ConvVAE, config: VisionConfig, epoch: int, extra: dict) -> None:
    save_tensors(
        folder / "vae.safetensors",
        {**{f"model.{k}": v for k, v in vae.state_dict().items()}, **extra},
    )
    write_json(
        folder / "vae.json",
        {"format": FORMAT, "epoch": epoch, "config": dataclasses.asdict(config)},
    )


def load_vae(folder: str | Path) -> tuple[ConvVAE, VisionConfig, int]:
    """The trained V of a run folder, its config and the epochs it has finished."""
    folder = Path(folder)
    config, epoch = _read_meta(folder)
    vae = ConvVAE(config.latent_dim)
    tensors = load_tensors(folder / "vae.safetensors", "V checkpoint")
    model = {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}
    load_state_dict_strict(vae, model, f"V checkpoint {folder / 'vae.safetensors'}")
    return vae, config, epoch


def load_classifier(folder: str | Path, latent_dim: int) -> LatentClassifier:
    classifier = LatentClassifier(latent_dim)
    path = Path(folder) / "classifier.safetensors"
    load_state_dict_strict(classifier, load_tensors(path, "latent classifier"), str(path))
    return classifier


def _read_meta(folder: Path) -> tuple[VisionConfig, int]:
    """Config and finished epochs from ``vae.json``, each malformation a CheckpointError."""
    path = folder / "vae.json"
    meta = read_json(path, "V checkpoint metadata")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a V checkpoint of this version")
    if not isinstance(meta.get("config"), dict) or not isinstance(meta.get("epoch"), int):
        raise CheckpointError(f"{path} lacks a config mapping or an integer epoch")
    return from_dict(VisionConfig, meta["config"], "vision"), meta["epoch"]


def resume_point(folder: Path, config: VisionConfig) -> int:
    """Epochs already finished by a compatible run in ``folder`` (0 for a new run)."""
    if not (folder / "vae.json").is_file():
        return 0
    saved, epoch = _read_meta(folder)
    if dataclasses.replace(saved, epochs=config.epochs) != config:
        raise CheckpointError(
            f"{folder} holds a V run with another config "
            f"({changed_fields(vars(saved), vars(config), skip=('epochs',))}); use a new "
            "folder or the same settings"
        )
    if epoch > config.epochs:
        raise CheckpointError(
            f"{folder} holds {epoch} finished epochs, more than the {config.epochs} asked for"
        )
    return epoch


def train_vae(
    config: VisionConfig,
    folder: str | Path,
    data: VisionData | None = None,
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
    device: str = "auto",
) -> dict[str, float]:
    """Train V as the paper, resuming from ``folder`` if it holds an unfinished run.

    Returns the last epoch's metrics. ``on_epoch(epoch, row)`` is called after every epoch.
    ``device``: ``auto`` (CUDA when there is one), ``cpu`` or ``cuda``.
    """
    dev = resolve_device(device)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    done = resume_point(folder, config)
    atomic_write_text(folder / "config.yaml", yaml.safe_dump(dataclasses.asdict(config)))
    data = data if data is not None else make_data(config)

    torch.manual_seed(config.seed)
    vae = ConvVAE(config.latent_dim).to(dev, memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(vae.parameters(), lr=config.lr)
    shuffle = torch.Generator().manual_seed(config.seed)  # the order of the images
    noise = torch.Generator(dev).manual_seed(config.seed + 1)  # eps of the reparameterization
    if done > 0:
        tensors = load_tensors(folder / "vae.safetensors", "V checkpoint")
        load_state_dict_strict(
            vae, {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}, "V checkpoint"
        )
        needed = ("rng.shuffle", "rng.noise")
        if any(k not in tensors for k in needed) or not any(
            k.startswith("optim.") for k in tensors
        ):
            raise CheckpointError(f"{folder / 'vae.safetensors'} lacks the optimizer or RNG state")
        optimizer_from_tensors(optimizer, tensors, "optim")
        try:
            shuffle.set_state(tensors["rng.shuffle"])
            noise.set_state(tensors["rng.noise"])
        except RuntimeError:
            raise CheckpointError(
                f"{folder} was trained on another device than {dev.type}; resume it there"
            ) from None
    logger = MetricsLogger(folder, resume_step=done)
    row: dict[str, float] = {}
    n = len(data.train_images)
    if n < config.batch_size:
        raise ConfigError(
            f"{n} training images are fewer than vision.batch_size ({config.batch_size})"
        )
    for epoch in range(done + 1, config.epochs + 1):
        start = time.perf_counter()
        sums, count = np.zeros(3), 0
        order = torch.randperm(n, generator=shuffle)
        batches = n // config.batch_size
        for b in range(batches):
            step = (epoch - 1) * batches + b  # updates before this one, over the whole run
            warmup = config.beta_warmup_steps
            beta = config.beta if warmup == 0 else config.beta * min(1.0, step / warmup)
            first = b * config.batch_size
            index = order[first : first + config.batch_size].numpy()
            x = to_input(data.train_images[np.sort(index)])
            x = x.to(dev, non_blocking=True).contiguous(memory_format=torch.channels_last)
            loss = vae.loss(x, beta, noise)
            optimizer.zero_grad(set_to_none=True)
            loss.total.backward()
            optimizer.step()
            sums += len(x) * np.array([float(v.detach()) for v in loss])
            count += len(x)
        train = sums / count
        test = evaluate_vae(vae, data.test_images, config.beta, config.seed + 1)
        for name, value in zip(("loss", "reconstruction", "kl"), train, strict=True):
            logger.record(f"train/{name}", value)
        for name, value in test.items():
            logger.record(f"test/{name}", value)
        logger.record("train/beta", beta)
        logger.record("time/epoch_seconds", time.perf_counter() - start)
        extra = {
            **optimizer_to_tensors(optimizer, "optim"),
            "rng.shuffle": shuffle.get_state(),
            "rng.noise": noise.get_state(),
        }
        row = logger.dump(epoch)  # the row first: a resume trims rows past the checkpoint
        save_vae(folder, vae, config, epoch, extra)
        if on_epoch is not None:
            on_epoch(epoch, row)
    logger.close()
    vae.cpu()
    has_classifier = (folder / "classifier.safetensors").is_file()
    if data.train_states is not None and (done < config.epochs or not has_classifier):
        fit_classifier(vae, config, data, folder)  # GesturePuzzle's macrostates from latents
    return row


def fit_classifier(
    vae: ConvVAE, config: VisionConfig, data: VisionData, folder: Path
) -> LatentClassifier:
    """Fit the latent classifier on training images' encoded means and one posterior sample of
    each, so it also reads latents drawn from N(mu, sigma) (what M's samples look like: noise
    of scale ~1 in the dimensions V leaves unused) and save it."""
    n = min(config.n_classifier_fit, len(data.train_images))
    mu, sigma = encode_images(vae, data.train_images[:n])
    generator = torch.Generator().manual_seed(config.seed)
    sample = mu + sigma * torch.randn(mu.shape, generator=generator)
    states = torch.as_tensor(data.train_states[:n])
    classifier = LatentClassifier(config.latent_dim)
    classifier.fit(torch.cat([mu, sample]), torch.cat([states, states]), seed=config.seed)
    save_tensors(folder / "classifier.safetensors", classifier.state_dict())
    return classifier
