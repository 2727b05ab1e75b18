"""The training loop around :class:`~imagine.learning.population.Population`: run folders, metrics,
M's accuracy, checkpoints, stop signals.

:func:`train_population` trains P agents (the seeds of one task and method) in lockstep, each
into its own run folder, resuming any that was stopped. Each agent writes its own metrics rows
(every ``log_every`` episodes), measures M's accuracy (every ``accuracy_every``), checkpoints
(every ``checkpoint_every``, at its budget and on SIGINT/SIGTERM) and stops at its own budget.
On a signal each agent finishes its episode and checkpoints; then :class:`Interrupted` is raised.
"""

from __future__ import annotations

import dataclasses
import signal
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from imagine.checkpoint import atomic_write_text
from imagine.config import AgentConfig
from imagine.devices import resolve_device
from imagine.errors import ConfigError, Interrupted, NumericalError
from imagine.learning.agent import Agent, check_folder, make_encoder, saved_config
from imagine.learning.agent_checkpoint import load_checkpoint, save_checkpoint, start_dynamics
from imagine.learning.population import Population
from imagine.metrics import MetricsLogger
from imagine.stopping import StopSignals


@dataclasses.dataclass
class PopulationResult:
    agents: list[Agent | None]
    """Each agent after its budget (None for one that failed)."""
    failures: dict[int, str]
    """A line for each agent that failed (by index), naming its folder."""


TRANSFERRED = ("encoder", "vae_run", "n_components", "model_residual",
               "model_ensemble")  # fmt: skip
"""What a run that starts M (``init_from``) must share with the agent: M's inputs and form."""


def dynamics_source(config: AgentConfig) -> Path:
    """The run whose MDN starts this agent's M: ``config.init_from``, or its ``seed-N``
    folder for this agent's seed when it has one; an error if it cannot serve."""
    folder = Path(str(config.init_from))
    if (folder / f"seed-{config.seed}").is_dir():
        folder = folder / f"seed-{config.seed}"
    source = saved_config(folder)
    if source is None:
        raise ConfigError(f"init_from: {folder} holds no agent run (no agent.json)")
    for name in TRANSFERRED:
        mine, theirs = getattr(config, name), getattr(source, name)
        if name == "vae_run" and mine is not None and theirs is not None:
            mine, theirs = Path(mine).resolve(), Path(theirs).resolve()
        if mine != theirs:
            raise ConfigError(
                f"init_from: {folder} has {name} {getattr(source, name)!r}, this agent "
                f"{getattr(config, name)!r}; M's dynamics transfer only between the same {name}"
            )
    if not source.trains_model:
        raise ConfigError(f"init_from: {folder} is a baseline run; it trained no M")
    return folder


def train_population(
    configs: Sequence[AgentConfig],
    folders: Sequence[str | Path],
    on_episode: Callable[[int, int, int, dict[str, float]], None] | None = None,
    threads: int | None = None,
    encoder: Any = None,
    device: str = "cpu",
) -> PopulationResult:
    """Train each ``configs[i]`` into ``folders[i]`` (resuming), all in one lockstep
    population. ``on_episode(i, episode, t, stats)`` is called after each of agent i's
    episodes (``t``: its real time steps so far; ``stats``: the episode's, such as
    ``charts/return`` and, where the environment reports it, ``charts/success``)."""
    if threads is not None:
        torch.set_num_threads(threads)
    folders = [Path(f) for f in folders]
    saved = [check_folder(config, folder) for config, folder in zip(configs, folders, strict=True)]
    torch_device = resolve_device(device)
    if encoder is None:
        encoder = make_encoder(configs[0], torch_device)
    population = Population(configs, encoder, torch_device)
    loggers = []
    saved_windows: list[dict[str, list[float]]] = [{} for _ in configs]
    for i, (config, folder) in enumerate(zip(configs, folders, strict=True)):
        folder.mkdir(parents=True, exist_ok=True)
        if saved[i] is not None:
            saved_windows[i] = load_checkpoint(population, i, folder)
        elif config.init_from is not None:
            start_dynamics(population, i, dynamics_source(config))
        atomic_write_text(folder / "config.yaml", yaml.safe_dump(dataclasses.asdict(config)))
        loggers.append(MetricsLogger(folder, resume_step=population.episode[i]))
        if population.finished(i):
            population.stop(i)
    windows = [defaultdict(list, w) for w in saved_windows]
    failures: dict[int, str] = {}
    with StopSignals() as stop:
        while any(population.active):
            for i, stats in population.step():
                for key, value in stats.items():
                    windows[i][key].append(value)
                _after_episode(population, i, folders[i], loggers[i], windows[i], stop.signal)
                if on_episode is not None:
                    on_episode(i, population.episode[i], population.t[i], stats)
            for i, message in sorted(population.failures.items()):
                failures[i] = f"{folders[i]}: {message}"
            population.failures.clear()
    for logger in loggers:
        logger.close()
    if stop.signal:
        name = signal.Signals(stop.signal).name
        where = ", ".join(str(f) for f in folders)
        raise Interrupted(
            f"{name}: stopped {where} with a checkpoint; run the same command again to resume",
            stop.signal,
        )
    agents = [None if i in failures else snapshot(population, i) for i in range(len(folders))]
    return PopulationResult(agents, failures)


def _after_episode(
    population: Population,
    i: int,
    folder: Path,
    logger: MetricsLogger,
    window: dict[str, list[float]],
    signal_number: int,
) -> None:
    """Agent i's episode just ended: accuracy, metrics row, checkpoint, stop at its budget."""
    config = population.configs[i]
    e = population.episode[i]
    probe = population.extras.model_probe  # GesturePuzzle: M over its 192 x 6
    if probe and population.config.trains_model and e % config.accuracy_every == 0:
        _, model = population.networks(i)
        for key, value in probe(model, population.encoder, config).items():
            logger.record(f"model/{key}_accuracy", value)
    if e % config.log_every == 0 or population.finished(i):
        for key, values in window.items():
            logger.record(key, float(np.mean(values)))
        logger.record("charts/time_steps", population.t[i])
        logger.dump(e)
        window.clear()
    finished = population.finished(i)
    if e % config.checkpoint_every == 0 or finished or signal_number:
        save_checkpoint(population, i, folder, dict(window))
    if finished or signal_number:
        population.stop(i)


def snapshot(population: Population, i: int) -> Agent:
    """Agent i as it is now, for evaluation and planning."""
    controller, model = population.networks(i)
    return Agent(population.configs[i], population.encoder, controller, model,
                 population.episode[i], population.t[i])  # fmt: skip


def train(
    config: AgentConfig,
    folder: str | Path,
    on_episode: Callable[[int], None] | None = None,
    threads: int | None = None,
    encoder: Any = None,
    device: str = "cpu",
) -> Agent:
    """Run Algorithm 1 into ``folder``, resuming a run that was stopped there. ``encoder``:
    one made already by :func:`make_encoder` (default: made here)."""
    result = train_population(
        [config], [folder], None if on_episode is None else lambda i, e, t, stats: on_episode(e),
        threads=threads, encoder=encoder, device=device,
    )  # fmt: skip
    if result.failures:
        raise NumericalError(result.failures[0].split(": ", 1)[1])
    return result.agents[0]
