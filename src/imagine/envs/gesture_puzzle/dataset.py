"""Synthesized image datasets for training V (paper section V-B: 100,000 training images and
10,000 test images).

A dataset file is safetensors (never pickle) holding ``train_images`` and ``test_images``
(uint8, (N, 64, 64, 3)) with the macrostates they show (``train_macrostates``,
``test_macrostates``, int64 (N, 4)), and the settings that made it as JSON metadata. Macrostates
are drawn uniformly over all 192, illegal and goal states included, so V sees every state the
agent can meet; fragments are drawn uniformly from each microstate's pool.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load_file, save_file

from imagine.checkpoint import fsync_file
from imagine.envs.gesture_puzzle.environment import FragmentSource, make_composer
from imagine.envs.gesture_puzzle.rules import N_MACROSTATES, all_macrostates
from imagine.envs.gesture_puzzle.scene import OBS_SIZE
from imagine.errors import ConfigError, DatasetFileError, ImagineError

SPLITS = ("train", "test")


@dataclass(frozen=True)
class DatasetConfig:
    """What a dataset file is made from."""

    n_train: int = 100_000
    """Training images (the paper's 100,000)."""
    n_test: int = 10_000
    """Test images (the paper's 10,000)."""
    seed: int = 0
    """Seed of the macrostates and fragments drawn; the test split uses its own stream."""
    fragments: str | None = None
    """Folder of fragment photographs; None for the procedural renderer."""
    fragment_seed: int = 0
    """Seed of the procedural renderer."""
    n_cube_fragments: int = 16
    """Procedural fragments per (cube, direction)."""
    n_hand_fragments: int = 50
    """Procedural fragments per pointed cube."""

    def __post_init__(self) -> None:
        if self.n_train < 1 or self.n_test < 1:
            raise ConfigError(
                f"n_train and n_test must be positive, got {self.n_train}, {self.n_test}"
            )


def synthesize(
    config: DatasetConfig,
    fragments: FragmentSource = None,
    chunk: int = 8192,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Images and macrostates of both splits; ``fragments`` overrides ``config.fragments``."""
    composer = make_composer(
        fragments if fragments is not None else config.fragments,
        config.fragment_seed,
        config.n_cube_fragments,
        config.n_hand_fragments,
    )
    streams = np.random.SeedSequence(config.seed).spawn(len(SPLITS))
    out: dict[str, np.ndarray] = {}
    for split, stream, n in zip(SPLITS, streams, (config.n_train, config.n_test), strict=True):
        rng = np.random.default_rng(stream)
        states = all_macrostates()[rng.integers(0, N_MACROSTATES, size=n)]
        images = np.empty((n, OBS_SIZE, OBS_SIZE, 3), dtype=np.uint8)
        for start in range(0, n, chunk):
            stop = min(start + chunk, n)
            images[start:stop] = composer.sample(rng, states[start:stop])
            if progress is not None:
                progress(stop - start)
        out[f"{split}_images"] = images
        out[f"{split}_macrostates"] = states
    return out


def save_dataset(path: str | Path, arrays: dict[str, np.ndarray], config: DatasetConfig) -> Path:
    """Write atomically: a temporary file beside ``path``, then a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    save_file(arrays, str(tmp), metadata={"imagine_dataset": json.dumps(asdict(config))})
    fsync_file(tmp)
    os.replace(tmp, path)
    return path


def load_dataset(path: str | Path) -> tuple[dict[str, np.ndarray], DatasetConfig]:
    """Read a dataset file; a clear :class:`DatasetFileError` for anything that is not one."""
    path = Path(path)
    if not path.is_file():
        raise DatasetFileError(f"dataset file {path} does not exist")
    try:
        arrays = load_file(str(path))
        from safetensors import safe_open

        with safe_open(str(path), framework="numpy") as f:
            meta = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as exc:
        raise DatasetFileError(f"{path} is not a readable safetensors dataset ({exc})") from None
    if "imagine_dataset" not in meta:
        raise DatasetFileError(f"{path} is a safetensors file but not an imagine dataset")
    for split in SPLITS:
        images, states = arrays.get(f"{split}_images"), arrays.get(f"{split}_macrostates")
        if images is None or states is None:
            raise DatasetFileError(f"{path} lacks the {split} split")
        if images.dtype != np.uint8 or images.shape[1:] != (OBS_SIZE, OBS_SIZE, 3):
            raise DatasetFileError(f"{path}: {split}_images must be uint8 (N, 64, 64, 3)")
        if states.shape != (len(images), 4):
            raise DatasetFileError(f"{path}: {split}_macrostates must be (N, 4), one per image")
    try:
        config = DatasetConfig(**json.loads(meta["imagine_dataset"]))
    except (json.JSONDecodeError, TypeError, ImagineError) as exc:
        raise DatasetFileError(f"{path} has unreadable dataset metadata ({exc})") from None
    for split, n in zip(SPLITS, (config.n_train, config.n_test), strict=True):
        states = arrays[f"{split}_macrostates"]
        if len(states) != n:
            raise DatasetFileError(f"{path}: {split} holds {len(states)} images, metadata says {n}")
        if (
            states.dtype.kind not in "iu"
            or (states < 0).any()
            or (states[:, :3] > 3).any()
            or (states[:, 3] > 2).any()
        ):
            raise DatasetFileError(f"{path}: {split}_macrostates are not valid (d0, d1, d2, h)")
    return arrays, config
