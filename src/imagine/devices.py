"""Where tensors live: ``--device auto|cpu|cuda`` for every command that trains."""

from __future__ import annotations

import os

import torch

from imagine.errors import ConfigError

AUTO_DEVICE = "IMAGINE_AUTO_DEVICE"
"""An environment variable: where ``auto`` goes when set (cpu or cuda). The tests set cpu, so
their bitwise checks (CPU arithmetic) hold on a machine with a GPU too."""


def resolve_device(device: str) -> torch.device:
    """``auto`` picks CUDA when there is one (or what ``$IMAGINE_AUTO_DEVICE`` says); ``cuda``
    without one is a config error."""
    if device == "auto":
        device = os.environ.get(AUTO_DEVICE) or "auto"
    if device not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"unknown device {device!r}; choose auto, cpu or cuda")
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was asked for but no CUDA device is available")
    return torch.device("cuda" if device != "cpu" and torch.cuda.is_available() else "cpu")
