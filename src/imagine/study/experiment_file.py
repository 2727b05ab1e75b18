"""Experiments as files: one YAML file per studied setting, holding its resolved configuration.

A file (``experiments/<name>.yaml``) names one agent of Algorithm 1 completely: its method and
every field of :class:`~imagine.config.AgentConfig` but those a study sets per run (task, seed,
budget, encoder, V). Nothing is merged over a preset, so the file means what it meant when it
ran, whatever the presets become; a field the library no longer has is a one-line error.

``imagine study FILE... --tasks --seeds --budgets --vae`` trains each file's agents (the seeds
of a task as one population), evaluates them at every budget, and prints and writes a table
(mean (std) and IQM [95% bootstrap interval] of success per task and budget). Every evaluation
it records carries the resolved config, the commit and V's hash
(:func:`imagine.study.provenance.provenance`).
"""

from __future__ import annotations

import dataclasses
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from imagine.config import AgentConfig, from_dict, load_yaml
from imagine.errors import ConfigError
from imagine.study.experiments import Job, frozen, load_evaluations
from imagine.study.report import iqm_interval

PER_RUN = ("task", "method", "seed", "episodes", "encoder", "vae_run")
"""AgentConfig fields a study sets for each run, never held by an experiment file."""


@dataclass(frozen=True)
class Experiment:
    """One studied agent: a name, what it tests, its method and its resolved settings."""

    name: str
    description: str
    method: str
    agent: dict[str, Any]
    """Every AgentConfig field but :data:`PER_RUN`."""

    def overrides(self) -> tuple[tuple[str, Any], ...]:
        """The settings that differ from AgentConfig's defaults (the paper's), as a Job holds
        them: the same agent, since a Job starts from those defaults (preset ``paper``)."""
        defaults = dataclasses.asdict(AgentConfig())
        return frozen(
            {k: v for k, v in self.agent.items() if k not in defaults or defaults[k] != v}
        )


def resolved(config: AgentConfig) -> dict[str, Any]:
    """An agent config's fields as an experiment file holds them."""
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in PER_RUN}


def load_experiment(path: str | Path) -> Experiment:
    """Read and check an experiment file: every field known, every value valid, none missing."""
    path = Path(path)
    document = load_yaml(path)
    for key in ("name", "method", "agent"):
        if key not in document:
            raise ConfigError(f"{path}: an experiment file needs '{key}'")
    agent = document["agent"]
    if not isinstance(agent, dict):
        raise ConfigError(f"{path}: 'agent' must be a mapping of AgentConfig fields")
    per_run = sorted(set(agent) & set(PER_RUN))
    if per_run:
        raise ConfigError(f"{path}: {', '.join(per_run)} are set per run by `imagine study`")
    missing = sorted(set(resolved(AgentConfig())) - set(agent))
    if missing:
        raise ConfigError(f"{path}: not resolved, missing {', '.join(missing)}")
    method = document["method"]
    try:  # unknown fields and bad values: ConfigError from from_dict / __post_init__
        from_dict(AgentConfig, {**agent, "method": method, "encoder": "oracle"}, "agent")
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None
    return Experiment(str(document["name"]), str(document.get("description", "")), method, agent)


def write_experiment(path: str | Path, experiment: Experiment) -> None:
    """Write an experiment file; a header comment lists what differs from the paper."""
    differs = ", ".join(f"{k}={v!r}" for k, v in experiment.overrides()) or "nothing"
    document = {"name": experiment.name, "description": experiment.description,
                "method": experiment.method, "agent": experiment.agent}  # fmt: skip
    head = f"{experiment.name}: differs from the paper's settings in {differs}"
    text = "".join(f"# {line}\n" for line in textwrap.wrap(head, 98))
    Path(path).write_text(text + yaml.safe_dump(document, sort_keys=False, width=100))


def experiment_jobs(
    experiment: Experiment,
    out: str | Path,
    tasks: tuple[str, ...],
    seeds: tuple[int, ...],
    budgets: tuple[int, ...],
    vae_run: str | None,
) -> list[Job]:
    """The runs of one experiment, ``out/<name>/<task>-<seed>``; the oracle without V."""
    common = {"budgets": tuple(sorted(set(budgets))), "preset": "paper", "vae_run": vae_run,
              "encoder": "oracle" if vae_run is None else "vae",
              "overrides": experiment.overrides()}  # fmt: skip
    folder = Path(out) / experiment.name
    return [
        Job(str(folder / f"{task}-{seed}"), task, experiment.method, seed, **common)
        for task in tasks
        for seed in seeds
    ]


def cell(values: list[float]) -> str:
    """Success % as mean (std) and IQM [95% bootstrap interval] over the seeds."""
    if not values:
        return "-"
    x = 100 * np.asarray(values, dtype=float)
    std = f" ({x.std(ddof=1):.1f})" if len(x) > 1 else ""
    return f"{x.mean():.1f}{std}, IQM {'{:.1f} [{:.1f}, {:.1f}]'.format(*iqm_interval(x))}"


def study_table(experiments: list[Experiment], jobs: dict[str, list[Job]], tasks, budgets) -> str:
    """A Markdown table: one row per experiment, one column per (task, budget)."""
    head = [f"{t} {b}" for t in tasks for b in sorted(set(budgets))]
    lines = ["| experiment | " + " | ".join(head) + " |", "| --- " * (len(head) + 1) + "|"]
    for experiment in experiments:
        rows = load_evaluations(jobs[experiment.name])
        cells = [cell([r["success"] for r in rows if r["task"] == t and r["budget"] == b])
                 for t in tasks for b in sorted(set(budgets))]  # fmt: skip
        lines.append(f"| {experiment.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
