"""Experiments as files (imagine.study.experiment_file, `imagine study`): every shipped file is
complete and valid, a file trains exactly the agent it was resolved from, a bad file is a
one-line error, and a study's records carry their config, commit and V's hash."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from imagine.config import agent_preset
from imagine.errors import ConfigError
from imagine.study.experiment_file import (
    Experiment,
    experiment_jobs,
    load_experiment,
    resolved,
    write_experiment,
)
from imagine.study.experiments import job_config

ROOT = Path(__file__).resolve().parents[1]
IMAGINE = str(Path(sys.executable).parent / "imagine")


@pytest.mark.parametrize(
    "path", sorted((ROOT / "experiments").glob("*.yaml")), ids=lambda p: p.stem
)
def test_every_shipped_experiment_file_is_resolved_and_valid(path):
    experiment = load_experiment(path)
    assert experiment.name == path.stem
    assert experiment.method in ("baseline", "augmented")


def test_experiment_files_exist_and_no_numbered_setting_is_left():
    assert len(list((ROOT / "experiments").glob("*.yaml"))) >= 10
    numbered = re.compile(r'"s[0-9]+"')
    for folder in ("scripts", "experiments", "src"):
        for file in (ROOT / folder).rglob("*"):
            if file.is_file() and file.suffix in (".py", ".yaml", ".md"):
                assert not numbered.search(file.read_text()), file


def test_a_file_trains_the_agent_it_was_resolved_from(tmp_path):
    """Resolved from today's `fast` augmented agent, a file's job has that agent's config for
    every per-run field, and no longer depends on the preset."""
    fast = agent_preset("fast", method="augmented")
    write_experiment(tmp_path / "fast.yaml", Experiment("fast", "", "augmented", resolved(fast)))
    experiment = load_experiment(tmp_path / "fast.yaml")
    job = experiment_jobs(experiment, tmp_path, ("hard",), (3,), (500,), "some/vae")[0]
    expected = agent_preset("fast", task="hard", seed=3, episodes=500, vae_run="some/vae")
    assert job_config(job, 500) == expected
    assert job.preset == "paper" and job.folder == str(tmp_path / "fast" / "hard-3")


def test_a_bad_experiment_file_names_what_is_wrong(tmp_path):
    good = resolved(agent_preset("fast"))
    path = tmp_path / "x.yaml"
    write_experiment(path, Experiment("x", "", "augmented", {**good, "model_updatez": 1}))
    with pytest.raises(ConfigError, match=r"unknown key agent\.model_updatez"):
        load_experiment(path)
    write_experiment(path, Experiment("x", "", "augmented", {**good, "seed": 1}))
    with pytest.raises(ConfigError, match="seed are set per run"):
        load_experiment(path)
    partial = {k: v for k, v in good.items() if k != "dropout"}
    write_experiment(path, Experiment("x", "", "augmented", partial))
    with pytest.raises(ConfigError, match="not resolved, missing dropout"):
        load_experiment(path)
    write_experiment(path, Experiment("x", "", "augmented", {**good, "dropout": 2.0}))
    with pytest.raises(ConfigError, match=r"dropout must be in \[0, 1\)"):
        load_experiment(path)


def test_imagine_study_runs_files_and_records_where_each_result_came_from(tmp_path):
    smoke = agent_preset("smoke", method="baseline", eval_episodes=20)
    write_experiment(tmp_path / "tiny.yaml", Experiment("tiny", "", "baseline", resolved(smoke)))
    out = tmp_path / "study"
    command = [
        IMAGINE,
        "study",
        str(tmp_path / "tiny.yaml"),
        "--out",
        str(out),
        "--oracle",
        "--tasks",
        "original",
        "--seeds",
        "0-1",
        "--budgets",
        "10,20",
        "--workers",
        "1",
    ]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    table = (out / "STUDY.md").read_text()
    assert table.splitlines()[0] == "| experiment | original 10 | original 20 |"
    assert table.splitlines()[2].startswith("| tiny | ") and "IQM" in table
    record = json.loads((out / "tiny" / "original-1" / "evaluation-00020.json").read_text())
    provenance = record["provenance"]
    experiment = load_experiment(tmp_path / "tiny.yaml")
    job = experiment_jobs(experiment, out, ("original",), (1,), (10, 20), None)[0]
    assert provenance["config"] == dataclasses.asdict(job_config(job, 20))
    assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?|unknown", provenance["commit"])
    assert provenance["vae_sha256"] is None  # the oracle: no V
    again = subprocess.run(command, capture_output=True, text=True, check=False)
    assert again.returncode == 0 and table == (out / "STUDY.md").read_text()  # read back
    wrong = subprocess.run([IMAGINE, "study", str(tmp_path / "tiny.yaml"), "--out", str(out)],
                           capture_output=True, text=True, check=False)  # fmt: skip
    assert wrong.returncode != 0 and "--vae RUN or --oracle" in wrong.stderr


def test_every_experiment_the_docs_cite_is_a_file():
    cited = set()
    for page in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]:
        text = page.read_text()
        cited |= set(re.findall(r"experiments/([a-z0-9-]+)\.yaml", text))
        for group in re.findall(r"experiments/\{([a-z0-9,-]+)\}\.yaml", text):
            cited |= set(group.split(","))
    missing = sorted(n for n in cited if not (ROOT / "experiments" / f"{n}.yaml").is_file())
    assert cited and not missing, missing


def test_a_file_with_wrappers_makes_hashable_jobs_that_keep_them(tmp_path):
    """A list field (``wrappers``) travels in a Job as a tuple and reaches the agent as a list."""
    wrappers = ["gymnasium.wrappers:FlattenObservation"]
    agent = resolved(agent_preset("fast", env="CartPole-v1", encoder="vector", wrappers=wrappers))
    write_experiment(tmp_path / "w.yaml", Experiment("w", "", "augmented", agent))
    experiment = load_experiment(tmp_path / "w.yaml")
    jobs = experiment_jobs(experiment, tmp_path, ("hard",), (0, 1), (500,), None)
    assert len({*jobs}) == 2
    assert job_config(jobs[0], 500).wrappers == wrappers
