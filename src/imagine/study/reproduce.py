"""`imagine reproduce`: the paper's experimental section as one command (docs/design.md section 3).

Into ``OUT``: ``vae/`` (V, trained once unless a V run is given), ``runs/<task>-<method>-<seed>/``
(every agent, evaluated at every budget), ``tables/`` (Tables I and II, Markdown and CSV),
``figures/`` (success against episodes, % increase, M's accuracy, V's reconstructions),
``random.json`` (the random agent) and ``REPORT.md``. Rerunning picks up where a stopped study
was: finished runs are read back, never run again. One process at a time: ``OUT`` is locked
while a study runs there.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from imagine.checkpoint import (
    atomic_write_text,
    changed_fields,
    read_json,
    with_defaults,
    write_json,
)
from imagine.config import (
    AGENT_PRESETS,
    VISION_PRESETS,
    agent_preset,
    check_imagines,
    check_preset,
    for_method,
)
from imagine.errors import ConfigError, Interrupted
from imagine.study.experiments import (
    EVAL_SEED,
    Job,
    LocalRunner,
    RayRunner,
    folder_lock,
    frozen,
    load_evaluations,
    study_jobs,
)
from imagine.study.peer import BASELINES, peer_evaluations, run_peers
from imagine.study.report import (
    accuracy_figure,
    claims,
    csv_text,
    curve_summary,
    curve_table,
    increase_figure,
    m_studies,
    success_figure,
    summarize,
    where_paper_stood,
    write_tables,
)

RANDOM_EPISODES = 10_000


STUDY_FIELDS = {
    "task": "use --tasks",
    "method": "a study trains both methods",
    "seed": "use --seeds",
    "episodes": "use --budgets",
    "encoder": "use --oracle",
    "vae_run": "use --vae",
}
"""Agent config fields a study sets per run, so --set may not: what to use instead."""


@dataclass(frozen=True)
class StudyConfig:
    """What `imagine reproduce` runs."""

    preset: str = "fast"
    tasks: tuple[str, ...] = ("original", "hard")
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    """The seeds of every (task, method); an integer n means seeds 0..n-1 (older study.yaml)."""
    budgets: tuple[int, ...] = (250, 500, 1000, 1500, 2000, 3000, 4000, 5000, 6000)
    """Where every run is evaluated: the paper's 2000..6000 and the fine learning curve before
    them, where the paper's baseline is weak."""
    backend: str = "local"
    workers: int = 2
    address: str | None = None
    vae_run: str | None = None
    """An existing V run to reuse; default: train V into OUT/vae with the preset."""
    oracle: bool = False
    """Feed C and M the true macrostate (no V)."""
    separate_runs: bool = False
    """One run per budget, each from scratch (the paper's wording), instead of one run per seed
    evaluated at every budget (statistically the same: exploration and memories do not depend
    on the budget)."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """Agent config fields over the preset (--set)."""
    device: str = "auto"
    """Where V and the populations train: auto (CUDA when there is one), cpu or cuda; stored
    resolved (cpu or cuda), so a study resumes on the kind of device it began on."""
    baselines: tuple[str, ...] = ()
    """Peer baselines beside ours (:mod:`imagine.study.peer`): ``sb3``, Stable-Baselines3's DQN
    on the same task, budgets and test episodes."""

    def __post_init__(self) -> None:
        from imagine.envs.gesture_puzzle.rules import TASKS

        check_preset(self.preset)
        for task in self.tasks:
            if task not in TASKS:
                raise ConfigError(f"unknown task {task!r}; choose from {', '.join(TASKS)}")
        if isinstance(self.seeds, int):
            object.__setattr__(self, "seeds", tuple(range(self.seeds)))
        object.__setattr__(self, "seeds", tuple(sorted(set(self.seeds))))
        if not self.seeds or min(self.seeds) < 0:
            raise ConfigError(f"seeds must be one or more non-negative integers, got {self.seeds}")
        for key in STUDY_FIELDS:
            if key in self.overrides:
                raise ConfigError(
                    f"--set {key}=...: the study sets {key} for each run ({STUDY_FIELDS[key]})"
                )
        if not self.budgets or min(self.budgets) < 1:
            raise ConfigError(f"budgets must be positive episode counts, got {self.budgets}")
        for baseline in self.baselines:
            if baseline not in BASELINES:
                raise ConfigError(
                    f"unknown baseline {baseline!r}; choose from {', '.join(BASELINES)}"
                )
        if self.backend not in ("local", "ray"):
            raise ConfigError(f"unknown backend {self.backend!r}; choose local or ray")
        from imagine.devices import resolve_device

        object.__setattr__(self, "device", resolve_device(self.device).type)
        if self.workers < 1:
            raise ConfigError(f"workers must be at least 1, got {self.workers}")
        # every budget's agent config must be valid before anything runs
        for budget in self.budgets:
            agent_preset(self.preset, episodes=budget, encoder="oracle", method="baseline",
                         **for_method(self.overrides, "baseline"))  # fmt: skip
            agent = agent_preset(self.preset, episodes=budget, encoder="oracle", **self.overrides)
        # the runs are evaluated early, but must imagine by the last budget
        check_imagines(agent, "--budgets")


STUDY_KEEP = ("backend", "workers", "address", "baselines")
"""The study settings that may change between runs of one study: how it runs, and its peer
baselines (which never change our runs)."""


def same_study(saved: dict[str, Any], config: StudyConfig) -> bool:
    """Whether a study folder's ``study.yaml`` (``saved``) is ``config``'s study: the same
    settings but for how it runs (backend, workers, address) and its peer baselines. An older
    file's seed count n reads as seeds 0..n-1; a setting added since it was written reads as
    its default."""
    return not study_changes(saved, config)


def study_changes(saved: dict[str, Any], config: StudyConfig) -> str:
    """The settings of ``config`` that differ from a study folder's ``study.yaml``
    (``saved``), ``name old -> new`` each (:func:`same_study`); empty if none."""
    saved = dict(saved or {})
    if isinstance(saved.get("seeds"), int):
        saved["seeds"] = list(range(saved["seeds"]))
    mine = yaml.safe_load(yaml.safe_dump(dataclasses.asdict(config)))
    return changed_fields(with_defaults(StudyConfig, saved), mine, skip=STUDY_KEEP)


def prepare_vision(config: StudyConfig, out: Path, log: Callable[[str], None]) -> str | None:
    """The V run the agents use: the given one, or V trained (or resumed) into OUT/vae."""
    if config.oracle:
        return None
    if config.vae_run is not None:
        return config.vae_run
    from imagine.config import vision_preset
    from imagine.models.vision_training import resume_point, train_vae

    folder = out / "vae"
    vision = vision_preset(config.preset)
    done = resume_point(folder, vision)
    if done == vision.epochs:
        log(f"V ({config.preset} preset) already trained in {folder}: read back")
    else:
        resumed = f", resuming after epoch {done} of {vision.epochs}" if done else ""
        log(f"training V ({config.preset} preset) into {folder}{resumed}")
        train_vae(vision, folder, device=config.device)
    if not (folder / "reconstructions.png").is_file():
        from imagine.envs.gesture_puzzle.vision_report import report_run

        report_run(folder)
    return str(folder)


def random_agents(
    tasks: tuple[str, ...], out: Path, hand_switch_prob: float = 0.0
) -> dict[str, float]:
    """Success rate of the random agent per task (cached in OUT/random.json), in the study's
    environment (a stochastic human's included)."""
    from imagine.envs.gesture_puzzle.evaluation import random_success

    path = out / "random.json"
    cached = read_json(path, "random-agent results") if path.is_file() else {}
    for task in tasks:
        if task not in cached:
            cached[task] = random_success(task, RANDOM_EPISODES, 0, hand_switch_prob)["success"]
    write_json(path, cached)
    return {task: cached[task] for task in tasks}


def deviations(preset: str) -> list[str]:
    """The preset's departures from the paper's settings, one line each."""
    by_method = AGENT_PRESETS[preset]
    fields = {**by_method["baseline"], **by_method["augmented"]}
    lines = [f"- agent `{k}` = {v!r}" + ("" if k in by_method["baseline"] else " (augmented)")
             for k, v in fields.items()
             if k != "episodes"]  # the budgets set the episodes  # fmt: skip
    lines += [f"- V `{k}` = {v!r}" for k, v in VISION_PRESETS[preset].items()]
    return lines or ["- none: every setting is the paper's"]


def write_report(config: StudyConfig, out: Path, jobs: list[Job], failures: list[str]) -> Path:
    """Tables, figures and REPORT.md from whatever evaluations exist."""
    evaluations = load_evaluations(jobs)
    if config.baselines:
        evaluations += peer_evaluations(out, config.tasks, config.seeds, config.budgets)
    if not evaluations:
        raise ConfigError(f"no finished evaluations in {out / 'runs'} to report")
    rows = summarize(evaluations)
    random = random_agents(config.tasks, out, config.overrides.get("hand_switch_prob", 0.0))
    tables = write_tables(out, rows, random)
    curves = curve_summary(evaluations)
    curves_md = curve_table(curves)
    atomic_write_text(out / "tables" / "curves.md", curves_md)
    atomic_write_text(out / "tables" / "curves.csv", csv_text(
        [{k: v for k, v in r.items() if k != "budgets"} for r in curves]))  # fmt: skip
    figures = out / "figures"
    figures.mkdir(exist_ok=True)
    made = [success_figure(rows, figures / "success.png"),
            increase_figure(rows, figures / "increase.png")]  # fmt: skip
    augmented = [Path(j.folder) for j in jobs if j.method == "augmented"]
    accuracy = accuracy_figure(augmented, figures / "model_accuracy.png")
    if accuracy is not None:
        made.append(accuracy)
    vae_run = jobs[0].vae_run if jobs else None
    if vae_run is not None and (Path(vae_run) / "reconstructions.png").is_file():
        shutil.copyfile(Path(vae_run) / "reconstructions.png", figures / "reconstructions.png")
        made.append(figures / "reconstructions.png")
    for job in jobs:  # seed 0's pictures of plans and generalization
        for kind in ("plan_rollout", "generalization"):
            for png in sorted(Path(job.folder).glob(f"{kind}-*.png")):
                if job.seed == 0:
                    target = figures / f"{kind}_{job.task}.png"
                    shutil.copyfile(png, target)
                    made.append(target)
    agent = agent_preset(config.preset, **config.overrides)
    text = [
        "# Reproduction of Thabet, Patacchiola and Cangelosi (2019), section V",
        "",
        f"Preset `{config.preset}`; tasks {', '.join(config.tasks)}; {len(config.seeds)} seeds; "
        f"budgets {', '.join(map(str, config.budgets))} training episodes; each agent tested "
        f"with {agent.eval_episodes} greedy episodes. Encoder: "
        f"{'oracle (true macrostate)' if config.oracle else f'V from `{vae_run}`'}. "
        f"Epsilon counts t as the {agent.eps_time}. "
        + (
            "One run per (seed, budget), each from scratch."
            if config.separate_runs
            else "One run per seed, evaluated at every budget."
        ),
        "",
        "## Deviations from the paper's settings",
        "",
        *deviations(config.preset),
        *[f"- `--set {k}={v!r}`" for k, v in config.overrides.items()],
        "",
        "## What our numbers say about the paper's claims",
        "",
        *claims(rows),
        *where_paper_stood(rows),
        *m_studies(evaluations),
        "",
        "## Learning curves",
        "",
        "Every run evaluated at every budget; the area under the success curve is the mean "
        "success over the span of the budgets (trapezoids), per seed, then mean and IQM with "
        "its 95% bootstrap interval over seeds.",
        "",
        curves_md,
    ]
    for task, table in tables.items():
        name = "Table I (original task)" if task == "original" else "Table II (hard task)"
        text += [f"## {name}", "", "Success % of greedy test episodes, mean (std) over seeds; "
                 "IQM with 95% bootstrap interval (rliable protocol); the paper's numbers at "
                 "right.", "", table]  # fmt: skip
    text += ["## Figures", "", *[f"![{p.stem}](figures/{p.name})" for p in made], ""]
    if failures:
        text += ["## Runs that failed", "", *[f"- {f}" for f in failures], ""]
    path = out / "REPORT.md"
    atomic_write_text(path, "\n".join(text))
    return path


def reproduce(
    config: StudyConfig,
    out: str | Path,
    log: Callable[[str], None] = print,
    on_start: Callable[[Job], None] | None = None,
    on_done: Callable[[Job, str | None], None] | None = None,
) -> tuple[Path, list[str]]:
    """Run the study into ``out``; returns REPORT.md's path and the failed runs' messages.
    Refused (:class:`~imagine.errors.FolderInUse`) while another process runs one there."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out, notice=log):
        return _run_study(config, out, log, on_start, on_done)


def _run_study(
    config: StudyConfig,
    out: Path,
    log: Callable[[str], None],
    on_start: Callable[[Job], None] | None,
    on_done: Callable[[Job, str | None], None] | None,
) -> tuple[Path, list[str]]:
    """:func:`reproduce` once ``out`` is locked."""
    saved = out / "study.yaml"
    mine = yaml.safe_dump(dataclasses.asdict(config))
    if saved.is_file() and not same_study(yaml.safe_load(saved.read_text()), config):
        raise ConfigError(f"{out} holds a study with other settings "
                          f"({study_changes(yaml.safe_load(saved.read_text()), config)}); "
                          "use a new folder")  # fmt: skip
    atomic_write_text(saved, mine)
    vae_run = prepare_vision(config, out, log)
    jobs = study_jobs(
        out, config.tasks, config.seeds, config.budgets, separate_runs=config.separate_runs,
        preset=config.preset,
        encoder="oracle" if config.oracle else "vae", vae_run=vae_run,
        overrides=frozen(config.overrides), plan_budget=max(config.budgets),
        generalize_budget=5000 if 5000 in config.budgets else max(config.budgets),
    )  # fmt: skip
    # the long (augmented) runs first, so no worker is left with one at the end
    todo = sorted(
        (job for job in jobs if not job.finished()), key=lambda j: j.method != "augmented"
    )
    log(f"{len(jobs) - len(todo)} of {len(jobs)} runs already finished")
    failures: list[str] = []

    def done(job: Job, error: str | None) -> None:
        if error is not None and "Interrupted" not in error:
            failures.append(error)
        if on_done is not None:
            on_done(job, error)

    if todo:
        runner = (
            LocalRunner(config.workers, config.device)
            if config.backend == "local"
            else RayRunner(config.workers, config.address, str(out / "ray"), config.device)
        )
        try:
            runner.run(todo, on_start or (lambda job: None), done)
        except Interrupted:  # Ctrl-C: the report of what has finished, then stop
            if load_evaluations(jobs):
                report = write_report(config, out, jobs, failures)
                log(f"stopped: {report} reports the runs finished so far; run the same command "
                    "again to resume")  # fmt: skip
            raise
    agent = agent_preset(config.preset, **config.overrides)
    run_peers(config.baselines, out, config.tasks, config.seeds, config.budgets,
              agent.eval_episodes, EVAL_SEED, agent.hand_switch_prob, log)  # fmt: skip
    return write_report(config, out, jobs, failures), failures
