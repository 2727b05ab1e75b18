"""The study of the paper's section V (DESIGN.md section 3) as independent jobs.

A :class:`Job` is one (task, method, seed) run of Algorithm 1 in its own folder. It trains to
the first budget, evaluates the greedy policy (1000 test episodes, batched) and M's accuracy,
writes ``evaluation-NNNNN.json``, and goes on to the next budget from its checkpoint:
exploration and the memories do not depend on the budget, so one run per seed evaluated at
each budget stands for one run per budget (DESIGN.md section 3). A job whose evaluation files
all exist is finished and is never run again; an unfinished one resumes from its last
checkpoint.

Jobs run behind one interface, :class:`Runner`: :class:`LocalRunner` (processes on this
machine, one torch thread each) or :class:`RayRunner` (a Ray cluster; ``pip install
imagine[ray]``). Both call :func:`run_job`, so the numbers do not depend on the backend.
"""

from __future__ import annotations

import multiprocessing
import os
import secrets
import signal
import tempfile
import traceback
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch

from imagine.checkpoint import read_json, write_json

EVAL_SEED = 1_000_000
"""Seed of the greedy test episodes (the same for every run and budget)."""


@dataclass(frozen=True)
class Job:
    """One (task, method, seed) run, evaluated at every budget."""

    folder: str
    task: str
    method: str
    seed: int
    budgets: tuple[int, ...]
    preset: str = "fast"
    encoder: str = "vae"
    vae_run: str | None = None
    overrides: tuple[tuple[str, Any], ...] = ()
    """Agent config fields over the preset, as (key, value) pairs."""
    plan_budget: int | None = None
    """Budget at which an augmented agent also generates plans (paper: 6000)."""
    generalize_budget: int | None = None
    """Budget at which an augmented agent's M is tested on terminal states (paper: 5000)."""

    @property
    def name(self) -> str:
        return f"{self.task}-{self.method}-{self.seed}"

    def evaluation_path(self, budget: int) -> Path:
        return Path(self.folder) / f"evaluation-{budget:05d}.json"

    def finished(self) -> bool:
        return all(self.evaluation_path(b).is_file() for b in self.budgets)


def study_jobs(
    out: str | Path,
    tasks: Iterable[str],
    seeds: int,
    budgets: Iterable[int],
    methods: Iterable[str] = ("baseline", "augmented"),
    separate_runs: bool = False,
    **common: Any,
) -> list[Job]:
    """Every (task, method, seed) job of a study, each in ``out/runs/<task>-<method>-<seed>``
    and evaluated at every budget; with ``separate_runs``, one job per budget as well, each
    trained from scratch (``.../<task>-<method>-<seed>-e<budget>``), as the paper describes."""
    budgets = tuple(sorted(set(budgets)))
    groups = [(f"-e{b}", (b,)) for b in budgets] if separate_runs else [("", budgets)]
    return [
        Job(
            str(Path(out) / "runs" / f"{task}-{method}-{seed}{suffix}"),
            task,
            method,
            seed,
            group,
            **common,
        )
        for task in tasks
        for method in methods
        for seed in range(seeds)
        for suffix, group in groups
    ]


def run_job(job: Job) -> list[dict[str, Any]]:
    """Train ``job`` through its budgets, evaluating at each; returns the evaluations. Safe to
    call again after a stop: finished budgets are read back, the run resumes where it was."""
    from imagine.errors import Interrupted
    from imagine.stopping import StopSignals

    torch.set_num_threads(1)  # pools and Ray reuse workers: set it in every job
    results = []
    with StopSignals() as stop:  # a signal between trainings stops before the next budget
        for budget in job.budgets:
            if stop.signal:
                raise Interrupted(f"{job.name} stopped before budget {budget}", stop.signal)
            results.append(_run_budget(job, budget))
    return results


def _run_budget(job: Job, budget: int) -> dict[str, Any]:
    """Train ``job`` to ``budget`` episodes (resuming) and evaluate it, or read that back."""
    from imagine.agent import train
    from imagine.config import agent_preset
    from imagine.evaluate import greedy_success, model_accuracy

    path = job.evaluation_path(budget)
    if path.is_file():
        return read_json(path, "evaluation")
    config = agent_preset(
        job.preset, task=job.task, method=job.method, seed=job.seed, episodes=budget,
        encoder=job.encoder, vae_run=job.vae_run, **dict(job.overrides),
    )  # fmt: skip
    agent = train(config, job.folder)
    result = greedy_success(
        agent.controller, agent.encoder, job.task, config.eval_episodes, EVAL_SEED
    )
    accuracy = None
    if agent.trains_model:
        accuracy = model_accuracy(agent.model, agent.encoder, job.task)
    result = {"task": job.task, "method": job.method, "seed": job.seed, "budget": budget,
              "time_steps": agent.t, **result, "model_accuracy": accuracy}  # fmt: skip
    result |= studies_of_m(job, agent, budget)
    write_json(path, result)
    return result


def studies_of_m(job: Job, agent, budget: int) -> dict[str, Any]:
    """Plans and generalization of an augmented agent at their budgets (with PNGs of the
    imagined rollout and of a prediction from a terminal state in the run folder)."""
    from imagine.generalization import generalization, generalization_png
    from imagine.planning import plan_trials, rollout_png, summarize_plans

    out: dict[str, Any] = {}
    if job.method != "augmented":
        return out
    folder = Path(job.folder)
    if budget == job.plan_budget:
        out["plans"] = summarize_plans(plan_trials(agent, 20, seed=job.seed))
        rollout_png(agent, folder / f"plan_rollout-{budget:05d}.png", seed=job.seed)
    if budget == job.generalize_budget:
        out["generalization"] = generalization(agent, 20, seed=job.seed)
        generalization_png(agent, folder / f"generalization-{budget:05d}.png", seed=job.seed)
    return out


class Runner(Protocol):
    """Runs jobs and reports each one as it ends."""

    def run(
        self,
        jobs: list[Job],
        on_start: Callable[[Job], None],
        on_done: Callable[[Job, str | None], None],
    ) -> None:
        """Run every job; ``on_done(job, error)`` gets None or a one-line error."""
        ...


def _guarded(job: Job) -> str | None:
    """:func:`run_job` with any failure turned into a message, so the other jobs go on."""
    try:
        run_job(job)
    except Exception as exc:  # a failed run must not stop the study
        last = traceback.format_exception_only(exc)[-1].strip()
        return f"{job.name}: {last}"
    return None


@dataclass
class LocalRunner:
    """Processes on this machine (spawned, one torch thread each)."""

    workers: int = 2

    def run(self, jobs, on_start, on_done) -> None:
        """SIGINT or SIGTERM stops the study cleanly: no new job starts, the signal goes on to
        the running ones (each checkpoints and stops), and :class:`Interrupted` is raised once
        they have."""
        from imagine.errors import ImagineError, Interrupted
        from imagine.stopping import StopSignals

        context = multiprocessing.get_context("spawn")
        with StopSignals() as stop, ProcessPoolExecutor(self.workers, mp_context=context) as pool:
            pending = {}
            queue = list(jobs)
            forwarded = False
            while queue or pending:
                while queue and len(pending) < self.workers and not stop.signal:
                    job = queue.pop(0)
                    on_start(job)
                    pending[pool.submit(_guarded, job)] = job
                if stop.signal and not forwarded:
                    for child in multiprocessing.active_children():
                        os.kill(child.pid, stop.signal)
                    forwarded = True
                if not pending:
                    break
                done, _ = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for future in done:
                    job = pending.pop(future)
                    try:
                        error = future.result()
                    except BrokenProcessPool:
                        error = f"{job.name}: its worker process died"
                    on_done(job, error)
                    if error is not None and "worker process died" in error:
                        for other in pending.values():
                            on_done(other, f"{other.name}: its worker process died")
                        raise ImagineError(
                            "a worker process died (killed, or out of memory); finished runs "
                            "are kept: run the same command again to resume"
                        )
        if stop.signal:
            name = signal.Signals(stop.signal).name
            raise Interrupted(
                f"{name}: the study stopped; running jobs wrote checkpoints; run the same "
                "command again to resume", stop.signal,
            )  # fmt: skip


@dataclass
class RayRunner:
    """A Ray cluster: ``address`` of an existing one, or a local instance bound to localhost,
    without a dashboard, its temporary files under ``temp_dir``."""

    workers: int = 2
    address: str | None = None
    temp_dir: str | None = None
    _link: Path | None = field(default=None, init=False, repr=False)

    def run(self, jobs, on_start, on_done) -> None:
        try:
            import ray
        except ImportError:
            from imagine.errors import ConfigError

            raise ConfigError("the ray backend needs Ray: pip install 'imagine[ray]'") from None
        started = not ray.is_initialized()
        if started:
            if self.address is not None:
                ray.init(address=self.address, include_dashboard=False, log_to_driver=False)
            else:
                # Our own instance: localhost only, no dashboard, no usage report, files under
                # temp_dir, and its auth token from the environment (Ray would otherwise write
                # one into the home folder).
                os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
                os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
                temp = self._short_temp_dir()
                ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=False,
                         _temp_dir=temp, _node_ip_address="127.0.0.1")  # fmt: skip
        try:
            remote = ray.remote(num_cpus=1)(_guarded)
            pending = {}
            for job in jobs:
                on_start(job)
                pending[remote.remote(job)] = job
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    on_done(pending.pop(ref), ray.get(ref))
        finally:
            if started:
                ray.shutdown()
            if self._link is not None:
                self._link.unlink()
                self._link.parent.rmdir()

    def _short_temp_dir(self) -> str | None:
        """``temp_dir``, through a short symlink in the system temp folder when its path is
        too long for Ray's Unix sockets (107 bytes in all)."""
        if self.temp_dir is None:
            return None
        folder = Path(self.temp_dir).resolve()
        folder.mkdir(parents=True, exist_ok=True)
        if len(str(folder)) <= 40:
            return str(folder)
        self._link = Path(tempfile.mkdtemp(prefix="imagine-ray-")) / "t"
        self._link.symlink_to(folder, target_is_directory=True)
        return str(self._link)


def load_evaluations(jobs: Iterable[Job]) -> list[dict[str, Any]]:
    """Every evaluation file the jobs have written so far."""
    return [
        read_json(job.evaluation_path(b), "evaluation")
        for job in jobs
        for b in job.budgets
        if job.evaluation_path(b).is_file()
    ]
