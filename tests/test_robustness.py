"""Robustness: NaN losses, SIGTERM and SIGKILL in the middle of a run, determinism, bad files
and bad settings on the command line (one line, non-zero exit, never a traceback)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.errors import NumericalError
from imagine.learning.population import Population
from imagine.learning.training import train
from imagine.metrics import read_metrics
from imagine.study.experiments import Job, LocalRunner

IMAGINE = str(Path(sys.executable).parent / "imagine")
SMOKE_RUN = ["--preset", "smoke", "--oracle", "--episodes", "120", "--set", "imagination_start=40",
             "--set", "checkpoint_every=20", "--set", "log_every=10"]  # fmt: skip


def numbers(folder: Path) -> list[dict[str, float]]:
    return read_metrics(folder / "metrics.csv")


def weights(folder: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return load_file(str(folder / "agent.safetensors"))


def same_weights(a: Path, b: Path) -> bool:
    x, y = weights(a), weights(b)
    return x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)


def test_a_nan_loss_stops_that_agent_naming_the_network_and_the_step():
    configs = [agent_preset("smoke", encoder="oracle", seed=s) for s in (0, 1)]
    population = Population(configs, OracleEncoder())
    with torch.no_grad():
        population.model.reward.layers[0].weight[0, 0, 0] = float("nan")  # agent 0's r-network
    for _ in range(50):
        population.step()
    assert population.active == [False, True]  # the other agent goes on
    assert population.failures[0].startswith("M's r-network loss became nan at real time step")


def test_a_single_run_with_a_nan_loss_raises(tmp_path, monkeypatch):
    original = Population.__init__

    def poisoned(self, *args, **kwargs):
        original(self, *args, **kwargs)
        with torch.no_grad():
            self.model.terminal.layers[0].weight[0, 0, 0] = float("nan")

    monkeypatch.setattr(Population, "__init__", poisoned)
    with pytest.raises(NumericalError, match=r"M's d-network loss became nan"):
        train(
            agent_preset("smoke", encoder="oracle", episodes=30, imagination_start=10),
            tmp_path / "run",
        )


def test_a_study_goes_on_when_one_run_diverges(tmp_path):
    common = {"preset": "smoke", "encoder": "oracle"}
    jobs = [Job(str(tmp_path / "bad"), "original", "augmented", 0, (30,),
                overrides=(("imagination_start", 10), ("model_lr", 1e30)), **common),
            Job(str(tmp_path / "good"), "original", "baseline", 0, (30,), **common)]  # fmt: skip
    errors = {}
    LocalRunner(1).run(jobs, lambda job: None, lambda job, e: errors.update({job.name: e}))
    assert "loss became" in errors["original-augmented-0"]
    assert errors["original-baseline-0"] is None and jobs[1].finished()


def test_same_seed_same_numbers(tmp_path):
    config = agent_preset("smoke", encoder="oracle", episodes=60, imagination_start=20)
    train(config, tmp_path / "a", threads=1)
    train(config, tmp_path / "b", threads=1)
    assert numbers(tmp_path / "a") == numbers(tmp_path / "b")
    assert same_weights(tmp_path / "a", tmp_path / "b")


@pytest.mark.parametrize(
    "stop", [signal.SIGTERM, pytest.param(signal.SIGKILL, marks=pytest.mark.slow)]
)
def test_a_run_stopped_mid_way_resumes_to_the_same_results(tmp_path, stop):
    straight, stopped = tmp_path / "straight", tmp_path / "stopped"
    done = subprocess.run([IMAGINE, "train", str(straight), *SMOKE_RUN], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    args = [IMAGINE, "train", str(stopped), *SMOKE_RUN]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (stopped / "agent.json").is_file():  # past the first checkpoint
        assert process.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    os.kill(process.pid, stop)
    _, err = process.communicate(timeout=60)
    if stop == signal.SIGTERM:
        assert process.returncode == 128 + signal.SIGTERM, err
        assert "stopped" in err and "checkpoint" in err and "Traceback" not in err
    else:
        assert process.returncode == -signal.SIGKILL
    assert not list(stopped.glob(".*.tmp"))  # no half-written file
    done = subprocess.run([IMAGINE, "train", str(stopped), *SMOKE_RUN], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert numbers(stopped) == numbers(straight)
    assert same_weights(stopped, straight)


def write_run(tmp_path: Path) -> Path:
    run = tmp_path / "run"
    train(agent_preset("smoke", encoder="oracle", episodes=10, method="baseline"), run, threads=1)
    return run


def cut_short(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def bad_inputs(tmp_path: Path) -> list[tuple[list[str], str]]:
    """(arguments, expected words in the one-line error) for the command line."""
    run = write_run(tmp_path)
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    for name in ("agent.json", "agent.safetensors", "config.yaml"):
        (truncated / name).write_bytes((run / name).read_bytes())
    cut_short(truncated / "agent.safetensors")
    other = tmp_path / "other"  # the same weights under a config of another architecture
    other.mkdir()
    for name in ("agent.safetensors", "config.yaml"):
        (other / name).write_bytes((run / name).read_bytes())
    meta = json.loads((run / "agent.json").read_text())
    meta["config"]["reward_hidden"] = 64
    (other / "agent.json").write_text(json.dumps(meta))
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "bad.yaml").write_text("a: [1,\n")
    return [
        (["train", "r", "--oracle", "--preset", "huge"], "preset"),
        (
            ["train", "r", "--oracle", "--config", str(tmp_path / "list.yaml")],
            "must hold a mapping",
        ),
        (["train", "r", "--oracle", "--config", str(tmp_path / "bad.yaml")], "not valid YAML"),
        (["train", "r", "--oracle", "--set", "real_batch=100000"], "must fit"),
        (["train", "r", "--oracle", "--set", "gamma=fast"], "gamma"),
        (["train", "r", "--oracle", "--set", "episodes=-5"], "must be positive"),
        (["train", "r", "--oracle", "--episodes", "10"], "beyond the episode budget"),
        (["train", "r", "--oracle", "--set", "epsilon_max=1"], "did you mean"),
        (["train", "r"], "no V run was given"),
        (["train", "r", "--vae", str(tmp_path / "nowhere")], "does not exist"),
        (["evaluate", str(tmp_path / "nowhere")], "holds no agent run"),
        (["evaluate", str(truncated)], "agent checkpoint"),
        (["evaluate", str(other)], "reward.net.0.weight"),
        (["reproduce", "s", "--budgets", "2000,x"], "comma-separated integers"),
        (["reproduce", "s", "--backend", "slurm"], "unknown backend"),
        (["reproduce", "s", "--tasks", "original,easy"], "unknown task"),
        (["reproduce", "s", "--seeds", "2-1"], "--seeds expects comma-separated integers"),
        (["reproduce", "s", "--seeds", "-1"], "--seeds expects comma-separated integers"),
        (["reproduce", "s", "--set", "task=hard"], "the study sets task for each run"),
        (["reproduce", "s", "--set", "seed=3"], "use --seeds"),
        (["train", "r", "--oracle", "--task", "hard", "--set", "task=original"], "given twice"),
        (["train", "r", "--no-oracle", "--set", "encoder=oracle"], "given twice"),
    ]


def test_every_bad_input_gets_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    from imagine.cli import main

    monkeypatch.chdir(tmp_path)
    cases = bad_inputs(tmp_path)
    for args, words in cases:  # in this process: `main` is the console script
        monkeypatch.setattr(sys, "argv", ["imagine", *args])
        with pytest.raises(SystemExit) as exit_:
            main()
        lines = capsys.readouterr().err.strip().splitlines()
        assert exit_.value.code == 2, (args, lines)
        assert len(lines) == 1 and lines[0].startswith("error:"), (args, lines)
        assert words in lines[0], (args, lines[0])
    args, words = cases[0]  # and once through the installed command itself
    done = subprocess.run([IMAGINE, *args], capture_output=True, text=True, check=False,
                          cwd=tmp_path)  # fmt: skip
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and words in lines[0], done.stderr
