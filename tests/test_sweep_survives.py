"""A sweep that survives its workers (issue 18): one process at a time runs a study folder, a
lock left by a dead process is taken over, and Ray reruns a population whose worker was killed,
from its last checkpoint."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import imagine.study.experiments as experiments
from imagine.errors import ConfigError, FolderInUse
from imagine.study.experiments import LOCK_FILE, Job, LocalRunner, RayRunner, folder_lock
from imagine.study.reproduce import StudyConfig, reproduce

IMAGINE = str(Path(sys.executable).parent / "imagine")
HOLD = """import sys, time
from imagine.study.experiments import folder_lock
with folder_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(600)
"""


def tiny_job(folder: Path, budgets: tuple[int, ...] = (10,)) -> Job:
    return Job(str(folder), "original", "baseline", 0, budgets, preset="smoke",
               encoder="oracle", overrides=(("eval_episodes", 20),))  # fmt: skip


def is_free(folder: Path) -> bool:
    """Whether nobody holds ``folder``'s lock (and nobody died holding it)."""
    notices: list[str] = []
    try:
        with folder_lock(folder, notice=notices.append):
            return not notices
    except FolderInUse:
        return False


def test_a_second_study_on_a_running_folder_is_refused_and_a_dead_holders_lock_taken_over(
    tmp_path,
):
    out = tmp_path / "study"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        second = subprocess.run([IMAGINE, "reproduce", str(out), "--preset", "smoke", "--seeds",
                                 "0", "--tasks", "original", "--budgets", "10", "--oracle",
                                 "--set", "imagination_start=5"],
                                capture_output=True, text=True, check=False)  # fmt: skip
        assert second.returncode == 2
        assert second.stderr.strip().splitlines() == [
            f"error: {out.resolve()} is in use by process {holder.pid} (-c {out}); wait for it "
            "to end or stop it, then run again"
        ]
        assert not (out / "study.yaml").exists()  # refused before it wrote anything
        with pytest.raises(FolderInUse, match=f"in use by process {holder.pid} "):
            LocalRunner(1).run([tiny_job(out / "run")], print, print)  # runners lock too
    finally:
        holder.kill()  # SIGKILL: no chance to release the lock itself
        holder.wait()
    assert (out / LOCK_FILE).read_text().startswith(f"{holder.pid}\n")  # left behind
    notices: list[str] = []
    with folder_lock(out, notice=notices.append):
        assert (out / LOCK_FILE).read_text().startswith(f"{os.getpid()}\n")
    assert notices == [
        f"{out.resolve()}: taking over the lock of process {holder.pid}, which died holding it"
    ]
    assert is_free(out)


RUN_LONG = """import sys
from imagine.study.experiments import Job, LocalRunner
job = Job(sys.argv[1], "original", "baseline", 0, (100000,), preset="smoke", encoder="oracle")
LocalRunner(1).run([job], lambda job: None, lambda job, error: None)
"""


def workers_of(pid: int) -> list[int]:
    """The spawned worker processes whose parent is ``pid`` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            command = (stat.parent / "cmdline").read_bytes()
        except OSError:  # ended meanwhile
            continue
        if int(fields[1]) == pid and b"spawn_main" in command:
            found.append(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl's parent-death signal")
def test_a_studys_workers_die_with_it_so_none_writes_on_after_its_lock_is_gone(tmp_path):
    """kill -9 of a study's own process (not its group) releases its lock; its worker must not
    go on training in the folder a second study may now take over."""
    study = subprocess.Popen([sys.executable, "-c", RUN_LONG, str(tmp_path / "runs" / "run")])
    try:
        deadline = time.monotonic() + 120
        while not (workers := workers_of(study.pid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert workers, "the study started no worker"
        assert not is_free(tmp_path / "runs")  # the study holds its folder
    finally:
        study.kill()
        study.wait()
    deadline = time.monotonic() + 30
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(pid) for pid in workers)


def test_the_lock_is_released_when_its_holder_raises(tmp_path):
    out = tmp_path / "study"
    (out / "study.yaml").parent.mkdir()
    (out / "study.yaml").write_text("preset: paper\n")  # another study's settings
    config = StudyConfig(preset="smoke", tasks=("original",), seeds=1, budgets=(10,),
                         oracle=True, overrides={"imagination_start": 5})  # fmt: skip
    with pytest.raises(ConfigError, match=r"other settings \(.*preset 'paper' -> 'smoke'"):
        reproduce(config, out, log=print)
    assert is_free(out)
    with pytest.raises(RuntimeError), folder_lock(out), folder_lock(out):  # re-entrant
        raise RuntimeError("boom")
    assert (out / LOCK_FILE).read_text() == "" and is_free(out)


def test_ray_reruns_a_killed_worker_and_the_run_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    pytest.importorskip("ray")
    from imagine.study.experiments import run_jobs

    killed, resumed = tmp_path / "killed", tmp_path / "resumed"

    def flaky(jobs, device="cpu"):
        """First attempt: the first budget (evaluated, checkpointed), then SIGKILL itself.
        Later ones: the whole job, noting the episode each agent resumes from."""
        from imagine.learning.population import Population

        if not killed.exists():
            run_jobs([dataclasses.replace(j, budgets=j.budgets[:1]) for j in jobs], device)
            first = jobs[0].evaluation_path(jobs[0].budgets[0]).stat().st_mtime_ns
            killed.write_text(f"{os.getpid()} {first}")
            os.kill(os.getpid(), signal.SIGKILL)
        load = Population.set_agent_state

        def noting_load(self, agent, tensors, values, where):
            load(self, agent, tensors, values, where)
            resumed.write_text(str(self.episode[agent]))

        Population.set_agent_state = noting_load
        return run_jobs(jobs, device)

    monkeypatch.setattr(experiments, "_guarded", flaky)  # what RayRunner sends to a worker
    job = tiny_job(tmp_path / "runs" / "run", budgets=(10, 20))
    errors = []
    RayRunner(1, temp_dir=str(tmp_path / "ray")).run(
        [job], lambda job: None, lambda job, error: errors.append(error)
    )
    assert errors == [None]
    pid, first = map(int, killed.read_text().split())
    assert pid != os.getpid()
    assert resumed.read_text() == "10"  # the retry trained on from the checkpoint at 10
    assert job.evaluation_path(10).stat().st_mtime_ns == first  # and did not redo budget 10
    evaluations = [json.loads(job.evaluation_path(b).read_text()) for b in (10, 20)]
    assert evaluations[1]["time_steps"] > evaluations[0]["time_steps"]
    assert is_free(tmp_path / "runs")
