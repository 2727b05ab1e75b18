"""Where tensors live: ``--device auto|cpu|cuda`` for every command that trains."""

from __future__ import annotations

import torch

from imagine.errors import ConfigError


def resolve_device(device: str) -> torch.device:
    """``auto`` picks CUDA when there is one; ``cuda`` without one is a config error."""
    if device not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"unknown device {device!r}; choose auto, cpu or cuda")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was asked for but no CUDA device is available")
    return torch.device("cuda" if device != "cpu" and torch.cuda.is_available() else "cpu")
