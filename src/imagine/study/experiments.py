"""The study of the paper's section V (docs/design.md section 3) as independent jobs.

A :class:`Job` is one (task, method, seed) run of Algorithm 1 in its own folder. It trains to
the first budget, evaluates the greedy policy (1000 test episodes, batched) and M's accuracy,
writes ``evaluation-NNNNN.json``, and goes on to the next budget from its checkpoint:
exploration and the memories do not depend on the budget, so one run per seed evaluated at
each budget stands for one run per budget (docs/design.md section 3). A job whose evaluation files
all exist is finished and is never run again; an unfinished one resumes from its last
checkpoint.

The jobs that differ only in their seed train together as one population
(:func:`population_groups`, :mod:`imagine.learning.population`): the seeds of a (task, method) in
lockstep in one process, each with exactly the numbers it would have alone.

Populations run behind one interface, :class:`Runner`: :class:`LocalRunner` (processes on this
machine, one torch thread each) or :class:`RayRunner` (a Ray cluster; ``pip install
imagine[ray]``). Both call :func:`run_jobs`, so the numbers do not depend on the backend.

One process at a time runs jobs in a folder: :func:`folder_lock` (a runner locks the folders
that hold its jobs' run folders, ``imagine reproduce`` its ``OUT`` as well).
"""

from __future__ import annotations

import dataclasses
import fcntl
import multiprocessing
import os
import secrets
import shlex
import signal
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch

from imagine.checkpoint import read_json, write_json

EVAL_SEED = 1_000_000
"""Seed of the greedy test episodes (the same for every run and budget)."""

LOCK_FILE = ".imagine.lock"
"""In a locked folder: the ``flock`` of the process running jobs there, and its PID and
command line, for the message of whoever finds it busy."""

RAY_RETRIES = 3
"""How many times Ray runs a population again whose worker died (killed, out of memory)."""

_held: dict[Path, int] = {}
"""The folders this process has locked, and its PID (a forked child holds none of them)."""


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
    seeds: int | Iterable[int],
    budgets: Iterable[int],
    methods: Iterable[str] = ("baseline", "augmented"),
    separate_runs: bool = False,
    **common: Any,
) -> list[Job]:
    """Every (task, method, seed) job of a study, each in ``out/runs/<task>-<method>-<seed>``
    and evaluated at every budget; with ``separate_runs``, one job per budget as well, each
    trained from scratch (``.../<task>-<method>-<seed>-e<budget>``), as the paper describes.
    ``seeds``: the seeds, or their number n (seeds 0..n-1)."""
    budgets = tuple(sorted(set(budgets)))
    seeds = range(seeds) if isinstance(seeds, int) else tuple(seeds)
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
        for seed in seeds
        for suffix, group in groups
    ]


def population_groups(jobs: Iterable[Job]) -> list[tuple[Job, ...]]:
    """The jobs grouped into populations: same settings and budgets, different seeds."""
    groups: dict[tuple, list[Job]] = {}
    for job in jobs:
        key = dataclasses.astuple(dataclasses.replace(job, folder="", seed=0))
        groups.setdefault(key, []).append(job)
    return [tuple(group) for group in groups.values()]


def run_jobs(jobs: Sequence[Job], device: str = "cpu") -> dict[str, str | None]:
    """Train ``jobs`` (one population: they differ only in seed) through their budgets,
    evaluating each agent at each; returns each job's error (None: finished). Safe to call again
    after a stop: finished budgets are read back, runs resume where they were."""
    from imagine.errors import Interrupted
    from imagine.stopping import StopSignals

    torch.set_num_threads(1)  # pools and Ray reuse workers: set it in every job
    errors: dict[str, str | None] = {job.name: None for job in jobs}
    with StopSignals() as stop:  # a signal between trainings stops before the next budget
        for budget in jobs[0].budgets:
            if stop.signal:
                raise Interrupted(f"{jobs[0].name} stopped before budget {budget}", stop.signal)
            running = [job for job in jobs if errors[job.name] is None]
            for job, error in zip(running, _run_budget(running, budget, device), strict=True):
                errors[job.name] = error
    return errors


def run_job(job: Job) -> list[dict[str, Any]]:
    """One job alone (a population of one); returns its evaluations."""
    error = run_jobs([job])[job.name]
    if error is not None:
        from imagine.errors import NumericalError

        raise NumericalError(error)
    return [read_json(job.evaluation_path(b), "evaluation") for b in job.budgets]


def job_config(job: Job, budget: int):
    """The agent config of ``job`` trained to ``budget`` episodes."""
    from imagine.config import agent_preset, for_method

    return agent_preset(
        job.preset, task=job.task, method=job.method, seed=job.seed, episodes=budget,
        encoder=job.encoder, vae_run=job.vae_run, **for_method(thawed(job.overrides), job.method),
    )  # fmt: skip


def frozen(overrides: dict[str, Any]) -> tuple[tuple[str, Any], ...]:
    """Agent config fields as a Job holds them: sorted pairs, lists (``wrappers``) as tuples,
    so that a Job stays hashable."""
    return tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in overrides.items()))


def thawed(overrides: tuple[tuple[str, Any], ...]) -> dict[str, Any]:
    """A Job's overrides as AgentConfig takes them (the inverse of :func:`frozen`)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in overrides}


def _run_budget(jobs: Sequence[Job], budget: int, device: str) -> list[str | None]:
    """Train ``jobs`` to ``budget`` episodes (resuming) and evaluate each, unless its
    evaluation is there already; each job's error or None."""
    from imagine.envs.gesture_puzzle.evaluation import (
        agent_success,
        hand_calibration,
        model_accuracy,
    )
    from imagine.learning.training import train_population
    from imagine.study.provenance import provenance

    todo = [job for job in jobs if not job.evaluation_path(budget).is_file()]
    if not todo:
        return [None] * len(jobs)
    configs = [job_config(job, budget) for job in todo]
    result = train_population(configs, [job.folder for job in todo], device=device)
    errors = {}
    for i, (job, agent) in enumerate(zip(todo, result.agents, strict=True)):
        if agent is None:
            errors[job.name] = f"{job.name}: {result.failures[i]}"
            continue
        p = agent.config.hand_switch_prob
        evaluation = agent_success(agent, agent.config.eval_episodes, EVAL_SEED)
        accuracy = None
        if agent.config.trains_model:
            accuracy = model_accuracy(agent.model, agent.encoder, job.task, p)
        evaluation = {"task": job.task, "method": job.method, "seed": job.seed,
                      "budget": budget, "time_steps": agent.t, **evaluation,
                      "model_accuracy": accuracy}  # fmt: skip
        if accuracy is not None and p > 0:  # a stochastic human: M's hand probabilities
            evaluation["hand_calibration"] = hand_calibration(agent.model, agent.encoder,
                                                              job.task, p)  # fmt: skip
        evaluation |= studies_of_m(job, agent, budget)
        evaluation["provenance"] = provenance(agent.config)
        write_json(job.evaluation_path(budget), evaluation)
    return [errors.get(job.name) for job in jobs]


def studies_of_m(job: Job, agent, budget: int) -> dict[str, Any]:
    """Plans and generalization of an augmented agent at their budgets (with PNGs of the
    imagined rollout and of a prediction from a terminal state in the run folder)."""
    from imagine.study.generalization import generalization, generalization_png
    from imagine.study.planning import plan_trials, rollout_png, summarize_plans

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


@contextmanager
def folder_lock(folder: str | Path, notice: Callable[[str], None] | None = None) -> Iterator[None]:
    """Hold ``folder``'s lock while the block runs; re-entrant within a process. A process
    that finds it held raises :class:`~imagine.errors.FolderInUse` naming the holder. The
    kernel releases the lock when its holder ends, however it ends (``kill -9`` too), so a lock
    file nobody holds is stale and is taken over, with ``notice`` when its holder died."""
    from imagine.errors import FolderInUse

    folder = Path(folder).resolve()
    if _held.get(folder) == os.getpid():
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid, command = _lock_holder(fd, wait=True)
            who = (f"process {pid}" + (f" ({command})" if command else "")) if pid else "a process"
            raise FolderInUse(
                f"{folder} is in use by {who}; wait for it to end or stop it, then run again"
            ) from None
        pid, _ = _lock_holder(fd)
        if pid is not None and notice is not None:  # a clean release leaves the file empty
            notice(f"{folder}: taking over the lock of process {pid}, which died holding it")
        me = f"{os.getpid()}\n{shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])}\n".encode()
        os.pwrite(fd, me, 0)
        os.ftruncate(fd, len(me))
        _held[folder] = os.getpid()
        try:
            yield
        finally:
            del _held[folder]
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the lock


def _lock_holder(fd: int, wait: bool = False) -> tuple[int | None, str]:
    """The PID and command line in a lock file (None: none); with ``wait``, up to a second for
    a live PID (a new holder writes its own just after taking the lock)."""
    for attempt in range(10 if wait else 1):
        time.sleep(0.1 if attempt else 0)
        lines = os.pread(fd, 4096, 0).decode(errors="replace").splitlines()
        pid = int(lines[0]) if lines and lines[0].isdigit() else None
        if pid is not None and (not wait or _alive(pid)):
            break
    return pid, lines[1] if pid is not None and len(lines) > 1 else ""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True


@contextmanager
def job_folders_locked(jobs: Iterable[Job]) -> Iterator[None]:
    """Every folder that holds run folders of ``jobs``, locked (:func:`folder_lock`)."""
    with ExitStack() as stack:
        for folder in sorted({Path(job.folder).parent for job in jobs}):
            stack.enter_context(folder_lock(folder))
        yield


class Runner(Protocol):
    """Runs jobs and reports each one as it ends, holding the lock of every folder that holds
    their run folders (:func:`job_folders_locked`) meanwhile."""

    def run(
        self,
        jobs: list[Job],
        on_start: Callable[[Job], None],
        on_done: Callable[[Job, str | None], None],
    ) -> None:
        """Run every job; ``on_done(job, error)`` gets None or a one-line error."""
        ...


def _guarded(jobs: tuple[Job, ...], device: str = "cpu") -> dict[str, str | None]:
    """:func:`run_jobs` with any failure turned into a message, so the other jobs go on."""
    try:
        return run_jobs(jobs, device)
    except Exception as exc:  # a failed population must not stop the study
        last = traceback.format_exception_only(exc)[-1].strip()
        return {job.name: f"{job.name}: {last}" for job in jobs}


@dataclass
class LocalRunner:
    """Processes on this machine (spawned, one torch thread each, killed if the study's process
    dies: :func:`imagine.stopping.die_with_parent`)."""

    workers: int = 2
    device: str = "cpu"

    def run(self, jobs, on_start, on_done) -> None:
        """SIGINT or SIGTERM stops the study cleanly: no new job starts, the signal goes on to
        the running ones (each checkpoints and stops), and :class:`Interrupted` is raised once
        they have."""
        from imagine.errors import ImagineError, Interrupted
        from imagine.stopping import StopSignals, start_study_worker

        context = multiprocessing.get_context("spawn")
        with (
            job_folders_locked(jobs),
            StopSignals() as stop,
            ProcessPoolExecutor(
                self.workers,
                mp_context=context,
                initializer=start_study_worker,
                initargs=(os.getpid(),),
            ) as pool,
        ):
            pending = {}
            queue = population_groups(jobs)
            forwarded = False
            while queue or pending:
                while queue and len(pending) < self.workers and not stop.signal:
                    group = queue.pop(0)
                    for job in group:
                        on_start(job)
                    pending[pool.submit(_guarded, group, self.device)] = group
                if stop.signal and not forwarded:
                    for child in multiprocessing.active_children():
                        os.kill(child.pid, stop.signal)
                    forwarded = True
                if not pending:
                    break
                done, _ = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for future in done:
                    group = pending.pop(future)
                    try:
                        errors = future.result()
                    except BrokenProcessPool:
                        errors = {job.name: f"{job.name}: its worker process died" for job in group}
                    for job in group:
                        on_done(job, errors[job.name])
                    if any(e is not None and "worker process died" in e for e in errors.values()):
                        for other in (job for g in pending.values() for job in g):
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
    without a dashboard, its temporary files under ``temp_dir``.

    A population whose worker dies (killed, out of memory, its node lost) is run again, up to
    :data:`RAY_RETRIES` times, and resumes where it was: :func:`run_jobs` reads back the budgets
    already evaluated and trains on from each run's last checkpoint. An error of our own code
    is never retried: :func:`_guarded` returns it as the job's error. A population that
    exhausts its retries is reported as failed and the others go on."""

    workers: int = 2
    address: str | None = None
    temp_dir: str | None = None
    device: str = "cpu"
    _link: Path | None = field(default=None, init=False, repr=False)

    def run(self, jobs, on_start, on_done) -> None:
        try:
            import ray
        except ImportError:
            from imagine.errors import ConfigError

            raise ConfigError("the ray backend needs Ray: pip install 'imagine[ray]'") from None
        with job_folders_locked(jobs):
            self._run(ray, jobs, on_start, on_done)

    def _run(self, ray, jobs, on_start, on_done) -> None:
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
            # a task that asks for no GPU sees none (Ray empties CUDA_VISIBLE_DEVICES)
            gpus = ray.cluster_resources().get("GPU", 0) if self.device != "cpu" else 0
            share = min(1.0, gpus / self.workers) if gpus else 0
            remote = ray.remote(num_cpus=1, num_gpus=share, max_retries=RAY_RETRIES,
                                retry_exceptions=False)(_guarded)  # fmt: skip
            pending = {}
            for group in population_groups(jobs):
                for job in group:
                    on_start(job)
                pending[remote.remote(group, self.device)] = group
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    try:
                        errors = ray.get(ref)
                    except ray.exceptions.RayError as exc:  # its worker died, past the retries
                        why = f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1]}"
                        errors = {job.name: f"{job.name}: {why}" for job in pending[ref]}
                    for job in pending.pop(ref):
                        on_done(job, errors[job.name])
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
