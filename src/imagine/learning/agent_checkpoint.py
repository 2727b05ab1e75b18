"""An agent's run folder on disk: ``agent.safetensors`` (tensors) and ``agent.json`` (the
rest), written atomically, never pickled.

:class:`~imagine.learning.population.Population` hands out and takes back an agent's state
(:meth:`~imagine.learning.population.Population.agent_state`); this module turns it into files and
back, checks the format, and reads a run for evaluation (:func:`read_networks`). The JSON holds
the format, episode and step counts, the environment's random stream where it has one, the
config, the device, and the episode statistics not yet averaged into a metrics row (``window``),
so a run stopped between rows resumes with the same rows.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from imagine.checkpoint import load_tensors, read_json, save_tensors, write_json
from imagine.errors import CheckpointError

FORMAT = "imagine-agent-3"
SAVED_FORMAT = "imagine-saved-agent-1"
"""An agent written by :meth:`~imagine.learning.agent.Agent.save`: networks only."""
READABLE_FORMATS = ("imagine-agent-2", FORMAT, SAVED_FORMAT)
"""Checkpoint formats whose networks can be loaded for evaluation (only FORMAT resumes)."""


def part(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors under ``prefix.``, with the prefix taken off."""
    return {k[len(prefix) + 1 :]: v for k, v in tensors.items() if k.startswith(prefix + ".")}


def save_checkpoint(
    population, agent: int, folder: Path, window: dict[str, list[float]] | None = None
) -> None:
    """Checkpoint one agent of a population into its run folder."""
    tensors, values = population.agent_state(agent)
    save_tensors(folder / "agent.safetensors", tensors)
    write_json(folder / "agent.json", {"format": FORMAT, **values, "window": window or {}})


def save_agent(folder: Path, tensors: dict[str, torch.Tensor], values: dict[str, Any]) -> Path:
    """Write a saved agent (:data:`SAVED_FORMAT`): its networks' tensors and its values; an
    error, before anything is written, if ``folder`` holds a training run (it would lose the
    memories and optimizers it resumes from)."""
    meta_path = folder / "agent.json"
    if meta_path.is_file():
        meta = read_json(meta_path, "agent checkpoint metadata")
        if not isinstance(meta, dict) or meta.get("format") != SAVED_FORMAT:
            raise CheckpointError(
                f"{folder} holds a training run; save the agent into another folder"
            )
    folder.mkdir(parents=True, exist_ok=True)
    save_tensors(folder / "agent.safetensors", tensors)
    write_json(folder / "agent.json", {"format": SAVED_FORMAT, **values})
    return folder


def read_checkpoint(
    folder: Path, formats: tuple[str, ...] = (FORMAT,)
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The tensors and values of a run folder's checkpoint; an error for another format."""
    meta = read_json(folder / "agent.json", "agent checkpoint metadata")
    if (
        isinstance(meta, dict)
        and meta.get("format") == SAVED_FORMAT
        and SAVED_FORMAT not in formats
    ):
        raise CheckpointError(
            f"{folder} holds a saved agent (Agent.save: networks only), not a run training resumes"
        )
    if not isinstance(meta, dict) or meta.get("format") not in formats:
        raise CheckpointError(f"{folder / 'agent.json'} is not an agent checkpoint of this version")
    return load_tensors(folder / "agent.safetensors", "agent checkpoint"), meta


def load_checkpoint(population, agent: int, folder: Path) -> dict[str, list[float]]:
    """Resume one agent of a population from its run folder (at the start of its next
    episode); returns its saved ``window``."""
    tensors, meta = read_checkpoint(folder)
    population.set_agent_state(agent, tensors, meta, str(folder / "agent.safetensors"))
    window = meta.get("window", {})
    return {k: [float(v) for v in vs] for k, vs in window.items()}


def start_dynamics(population, agent: int, source: Path) -> None:
    """Agent ``agent``'s MDN from the run in ``source`` (``init_from``)."""
    tensors, _ = read_checkpoint(source, READABLE_FORMATS)
    population.start_dynamics_from(agent, tensors, str(source / "agent.safetensors"))
