"""`imagine reproduce`: every table, figure and report file; reruns that run nothing new; a
study killed mid-way that resumes without redoing finished runs; Ray gives local's numbers."""

import csv
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from imagine.config import parse_seeds
from imagine.errors import ConfigError
from imagine.study.experiments import Job, LocalRunner, RayRunner, run_job, study_jobs
from imagine.study.report import (
    claims,
    iqm_interval,
    markdown_table,
    summarize,
    where_paper_stood,
)
from imagine.study.reproduce import StudyConfig, same_study

IMAGINE = str(Path(sys.executable).parent / "imagine")
SMOKE = ["--preset", "smoke", "--seeds", "0,1", "--set", "imagination_start=10",
         "--set", "accuracy_every=20"]  # fmt: skip


def reproduce(out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([IMAGINE, "reproduce", str(out), *SMOKE, *args],
                          capture_output=True, text=True, check=False)  # fmt: skip


def evaluation_times(out: Path) -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns for p in sorted(out.glob("runs/*/evaluation-*.json"))}


def test_smoke_study_writes_every_file_and_a_rerun_runs_nothing(tmp_path):
    out = tmp_path / "study"
    done = reproduce(out, "--tasks", "original,hard", "--budgets", "20,40")
    assert done.returncode == 0, done.stderr
    for name in ["REPORT.md", "random.json", "tables/table_original.md", "tables/table_hard.md",
                 "tables/table_original.csv", "tables/table_hard.csv", "figures/success.png",
                 "figures/increase.png", "figures/model_accuracy.png",
                 "figures/reconstructions.png", "figures/plan_rollout_original.png",
                 "figures/generalization_hard.png"]:  # fmt: skip
        assert (out / name).is_file(), name
    assert len(list(out.glob("runs/*/evaluation-*.json"))) == 2 * 2 * 2 * 2
    progress = re.findall(r"study: (\d+)/320 episodes \(\d+%\).*, \d+:\d\d elapsed, ETA",
                          done.stderr)  # fmt: skip
    assert progress and progress[-1] == "320", done.stderr  # a log file's lines, in episodes
    table = (out / "tables" / "table_original.md").read_text().splitlines()
    assert table[0].startswith("| Episodes | Base DQN | Augmented | % increase")
    assert [line.split("|")[1].strip() for line in table[2:]] == ["20", "40", "random agent"]
    assert all(line.count("|") == 10 for line in table)
    with open(out / "tables" / "table_hard.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["budget"], r["method"]) for r in rows] == [
        ("20", "baseline"),
        ("20", "augmented"),
        ("40", "baseline"),
        ("40", "augmented"),
    ]
    assert {"mean", "std", "iqm", "iqm_low", "iqm_high", "paper_mean", "n"} <= set(rows[0])
    report = (out / "REPORT.md").read_text()
    assert "Table I (original task)" in report and "Table II (hard task)" in report
    assert "Deviations from the paper" in report and "claims" in report
    assert "No claims**: 2 seeds" in report and "beats baseline" not in report  # 2 seeds
    assert "original, plans" in report and "hard, model generalization" in report
    assert "## Learning curves" in report and "area under the success curve" in report
    curves = (out / "tables" / "curves.md").read_text().splitlines()
    assert len(curves) == 2 + 2 * 2  # header, rule, (task, method) rows
    assert (out / "tables" / "curves.csv").is_file()
    last = json.loads((out / "runs" / "hard-augmented-1" / "evaluation-00040.json").read_text())
    assert last["plans"]["trials"] == 20 and last["generalization"]["trials"] == 20
    before = evaluation_times(out)
    again = reproduce(out, "--tasks", "original,hard", "--budgets", "20,40")
    assert again.returncode == 0, again.stderr
    assert "8 of 8 runs already finished" in again.stderr
    assert "training V" in done.stderr and "training V" not in again.stderr
    assert re.search(r"V \(smoke preset\) already\s+trained\s+in.*read\s*back", again.stderr, re.S)
    assert evaluation_times(out) == before


@pytest.mark.parametrize(
    ("stop", "workers"),
    [
        (signal.SIGKILL, "1"),
        # to the process group, as `timeout` or `kill -- -PGID` do (slow: CI's 15-minute margin)
        pytest.param(signal.SIGTERM, "2", marks=pytest.mark.slow),
        pytest.param(signal.SIGTERM, "1", marks=pytest.mark.slow),
    ],
    ids=["SIGKILL-all", "SIGTERM-all", "SIGTERM-main"],
)
def test_a_killed_study_resumes_without_redoing_finished_runs(tmp_path, stop, workers):
    out = tmp_path / "study"
    args = [IMAGINE, "reproduce", str(out), *SMOKE, "--tasks", "original", "--oracle",
            "--budgets", "30,60", "--workers", workers]  # fmt: skip
    log = (tmp_path / "stderr.txt").open("w")
    process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=log,
                               start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + 240
    while len(evaluation_times(out)) < 3 and process.poll() is None:
        assert time.monotonic() < deadline, "the study never got going"
        time.sleep(0.2)
    if stop == signal.SIGKILL:  # the whole study, workers included, dies at once
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    elif workers == "2":  # the whole process group is told (as by Ctrl-C), workers too
        os.killpg(process.pid, stop)
        try:  # the study forwards the signal too: a worker that stopped must not die of it
            process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            raise AssertionError(f"the study hung after {stop.name}") from None
        err = (tmp_path / "stderr.txt").read_text()
        assert process.returncode == 128 + stop, err
        assert "worker process died" not in err
        assert (out / "REPORT.md").is_file()
    else:  # only the main process is told; it stops its workers cleanly
        os.kill(process.pid, signal.SIGTERM)
        assert process.wait(timeout=120) == 128 + signal.SIGTERM
        assert (out / "REPORT.md").is_file()  # the report of what had finished
    finished = evaluation_times(out)
    assert 0 < len(finished) < 8, "kill the study mid-way"
    contents = {p: Path(p).read_text() for p in finished}
    done = subprocess.run(args, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    after = evaluation_times(out)
    assert len(after) == 2 * 2 * 2
    assert {p: after[p] for p in finished} == finished  # nothing finished was redone
    assert {p: Path(p).read_text() for p in finished} == contents
    assert not list(out.rglob(".*.tmp"))  # no half-written file left behind


def test_ray_backend_gives_the_local_numbers(tmp_path):
    try:
        import ray  # noqa: F401
    except ImportError:
        pytest.skip("Ray is not installed (pip install 'imagine[ray]')")
    jobs = [Job(str(tmp_path / backend / "run"), "original", "augmented", 0, (30,),
                preset="smoke", encoder="oracle", overrides=(("imagination_start", 15),))
            for backend in ("local", "ray")]  # fmt: skip
    errors = []
    LocalRunner(1).run([jobs[0]], lambda job: None, lambda job, e: errors.append(e))
    try:
        RayRunner(1, temp_dir=str(tmp_path / "ray-tmp")).run(
            [jobs[1]], lambda job: None, lambda job, e: errors.append(e)
        )
    except Exception as exc:  # Ray present but unable to start here
        pytest.skip(f"Ray could not start: {exc}")
    assert errors == [None, None]
    local, remote = (json.loads(job.evaluation_path(30).read_text()) for job in jobs)
    assert local == remote


def test_run_job_reads_back_finished_budgets(tmp_path):
    job = Job(str(tmp_path / "run"), "original", "baseline", 0, (20,), preset="smoke",
              encoder="oracle")  # fmt: skip
    first = run_job(job)
    mtime = job.evaluation_path(20).stat().st_mtime_ns
    assert run_job(job) == first and job.evaluation_path(20).stat().st_mtime_ns == mtime
    assert first[0]["model_accuracy"] is None  # a baseline does not train M


def test_statistics_and_tables():
    values = np.array([10.0, 20.0, 30.0, 40.0, 100.0])
    iqm, low, high = iqm_interval(values)
    assert iqm == pytest.approx(30.0)  # trims one run from each end of five
    assert low <= iqm <= high
    evaluations = [{"task": "hard", "budget": 2000, "method": m, "seed": s,
                    "success": (0.5 if m == "baseline" else 0.6) + 0.01 * s}
                   for m in ("baseline", "augmented") for s in range(5)]  # fmt: skip
    rows = summarize(evaluations)
    assert [r["method"] for r in rows] == ["baseline", "augmented"]
    assert rows[0]["mean"] == pytest.approx(52.0) and rows[0]["paper_mean"] == 30.12
    table = markdown_table("hard", rows, 0.0339)
    assert "| 2000 | 52.00 (1.58) | 62.00 (1.58) | 19.23 |" in table
    assert "30.12 (4.16) | 53.78 (3.16) | 78.55 |" in table
    assert "3.39" in table.splitlines()[-1]
    said = "\n".join(claims(rows))
    assert "hard: augmented beats baseline** (supported" in said
    assert "at least as good as the paper's**: at 1 of 1 budgets (2000)" in said
    for seeds in (1, 2):  # too few seeds: one line, and no claim
        few = summarize([e for e in evaluations if e["seed"] < seeds])
        (line,) = claims(few)
        assert f"No claims**: {seeds} seed" in line and "at least 3 seeds" in line
        assert "beats" not in line and "supported" not in line
        assert where_paper_stood(few) == []
    assert where_paper_stood(rows)  # 5 seeds: said


@pytest.mark.parametrize(
    "values, message",
    [
        ({"tasks": ("easy",)}, "unknown task"),
        ({"seeds": 0}, "seeds must be one or more non-negative integers"),
        ({"seeds": (1, -2)}, "seeds must be one or more non-negative integers"),
        ({"overrides": {"episodes": 9}}, "the study sets episodes"),
        ({"budgets": ()}, "budgets must be positive"),
        ({"backend": "slurm"}, "unknown backend"),
        ({"preset": "huge"}, "preset"),
        ({"budgets": (80,)}, "beyond the episode budget"),  # fast: I_start 100
    ],
)
def test_bad_study_settings(values, message):
    with pytest.raises(ConfigError, match=message):
        StudyConfig(**values)


def test_a_study_lists_its_seeds_and_reads_an_older_count():
    assert StudyConfig(seeds=(4, 1, 4)).seeds == (1, 4)
    assert StudyConfig(seeds=3).seeds == (0, 1, 2)  # study.yaml before seeds were listed
    assert parse_seeds("0-2,7, 1") == (0, 1, 2, 7) and parse_seeds("5") == (5,)
    older = yaml.safe_load(yaml.safe_dump(dataclasses.asdict(StudyConfig())))
    older["seeds"], older["workers"] = 5, 1
    assert same_study(older, StudyConfig(workers=2))  # make run's study.yaml before the change
    assert not same_study(older, StudyConfig(seeds=(0, 1, 2, 3)))
    del older["separate_runs"]  # written before the setting existed: it measured the default
    assert same_study(older, StudyConfig(workers=2))
    assert not same_study(older, StudyConfig(separate_runs=True))
    jobs = study_jobs("out", ["hard"], (3, 7), [1000])
    assert [job.name for job in jobs] == [f"hard-{m}-{s}" for m in ("baseline", "augmented")
                                          for s in (3, 7)]  # fmt: skip


def test_one_run_per_seed_or_one_per_budget(tmp_path):
    shared = study_jobs(tmp_path, ["hard"], 2, [3000, 2000])
    assert len(shared) == 4 and all(job.budgets == (2000, 3000) for job in shared)
    separate = study_jobs(tmp_path, ["hard"], 2, [3000, 2000], separate_runs=True)
    assert len(separate) == 8 and {job.budgets for job in separate} == {(2000,), (3000,)}
    assert len({job.folder for job in separate}) == 8
