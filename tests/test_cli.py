"""The `imagine` command: help everywhere, the contact sheet, one-line errors."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

IMAGINE = str(Path(sys.executable).parent / "imagine")


def run(*args):
    return subprocess.run([IMAGINE, *args], capture_output=True, text=True, check=False)


def test_help():
    done = run("--help")
    assert done.returncode == 0 and "Usage" in done.stdout


def every_command():
    """(words, command) for the `imagine` command and each of its subcommands."""
    from typer.main import get_command

    from imagine.cli import app

    def walk(command, words):
        yield words, command
        for name, sub in sorted(getattr(command, "commands", {}).items()):
            yield from walk(sub, [*words, name])

    return list(walk(get_command(app), []))


COMMANDS = every_command()


@pytest.mark.parametrize(
    "words, command", COMMANDS, ids=[" ".join(["imagine", *w]) for w, _ in COMMANDS]
)
def test_help_reads_well(words, command):
    """Each command's summary is one sentence on one line (the command list shows it whole),
    and no option shows a bare type such as <str> where a metavar says what it takes (nor <bool>
    beside a flag, which takes no value)."""
    import inspect

    from typer.testing import CliRunner

    from imagine.cli import app

    summary = inspect.cleandoc(command.help or "").split("\n\n")[0]
    assert summary and "\n" not in summary and len(summary) <= 90, summary
    done = CliRunner().invoke(app, [*words, "--help"], env={"COLUMNS": "100"})
    assert done.exit_code == 0 and "Usage" in done.output
    assert summary.split()[-1] in done.output  # the summary whole, not cut
    for bare in ("<str>", "<list[", "<dict", "<bool>"):
        assert bare not in done.output, (words, done.output)


def test_env_show_writes_a_contact_sheet(tmp_path):
    out = tmp_path / "sheet.png"
    done = run("env", "show", "--task", "hard", "--seed", "0", "--out", str(out))
    assert done.returncode == 0, done.stderr
    with Image.open(out) as img:
        pixels = np.asarray(img.convert("L"))
    assert pixels.shape[0] > 500 and pixels.shape[1] > 500
    assert pixels.std() > 20  # a picture, not a blank page


def test_export_fragments_round_trips(tmp_path):
    folder = tmp_path / "frags"
    assert (
        run(
            "env",
            "export-fragments",
            str(folder),
            "--n-cube-fragments",
            "2",
            "--n-hand-fragments",
            "3",
        ).returncode
        == 0
    )
    assert len(list((folder / "cube2" / "left").glob("*.png"))) == 2
    assert len(list((folder / "hand" / "cube1").glob("*.png"))) == 3
    again = run("env", "export-fragments", str(folder), "--n-cube-fragments", "1",
                "--n-hand-fragments", "1")  # fmt: skip
    assert again.returncode == 0  # a smaller export leaves no stale fragments behind
    assert len(list((folder / "cube2" / "left").glob("*.png"))) == 1
    done = run("env", "show", "--fragments", str(folder), "--out", str(tmp_path / "s.png"))
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["env", "show", "--fragments", "/no/such/folder"], "does not exist"),
        (["dataset", "x.safetensors", "--n-train", "0"], "must be positive"),
        (["train", "r", "--oracle", "--set", "dropout"], "KEY=VALUE"),
        (["train", "r", "--oracle", "--set", "dropuot=0.1"], "did you mean 'dropout'"),
        (["train", "r", "--oracle", "--config", "missing.yaml"], "does not exist"),
        (["train", "r", "--env", "CartPole-v1"], "needs a budget: give --steps N"),
        (
            ["train", "r", "--preset", "smoke", "--oracle", "--episodes", "20"],
            "(--episodes 200 works) or start imagining earlier (--set imagination_start=10)",
        ),
        (["vae", "train", "--out", "v", "--set", "beta=-1"], "vision.beta must be >= 0"),
        (["vae", "train", "--out", "v", "--set", "betta=8"], "did you mean 'beta'"),
    ],
)
def test_user_errors_are_one_line_and_exit_2(tmp_path, args, message):
    done = subprocess.run(
        [IMAGINE, *args], capture_output=True, text=True, check=False, cwd=tmp_path
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0]
    assert "Traceback" not in done.stderr


def test_unknown_task_is_rejected():
    done = run("env", "show", "--task", "easy")
    assert done.returncode == 2 and "easy" in done.stderr and "Traceback" not in done.stderr


def test_train_progress_in_a_log_names_its_unit_and_the_recent_outcome(tmp_path):
    """Off a terminal (a log file) the training bar is a plain line every 5%: done/total in
    episodes (or steps), the recent return and success, the elapsed time and the ETA."""
    import re

    from typer.testing import CliRunner

    from imagine.cli import app

    args = ["train", str(tmp_path / "run"), "--preset", "smoke", "--oracle", "--episodes", "20",
            "--set", "imagination_start=10", "--method", "baseline"]  # fmt: skip
    done = CliRunner().invoke(app, args)
    assert done.exit_code == 0, done.output
    pattern = (r"baseline original seed 0: (\d+)/20 episodes \(\d+%\), return -?\d+\.\d\d, "
               r"success \d+% \(last (\d+) episodes\), \d+:\d\d elapsed, ETA")  # fmt: skip
    found = [(int(m.group(1)), int(m.group(2))) for m in re.finditer(pattern, done.output)]
    counts = [count for count, _ in found]
    assert counts == sorted(counts) and counts[-1] == 20 and 3 <= len(counts) <= 21, done.output
    assert all(last == min(count, 20) for count, last in found)  # the episodes averaged
    lines = done.output.splitlines()  # the last lines whole, each labelled
    run = tmp_path / "run"
    assert f"trained {run}: 20 episodes, " in lines[-2] and lines[-2].endswith(
        f"; next: imagine evaluate {run}")  # fmt: skip
    assert re.fullmatch(r"trained in \d+ s", lines[-1]), lines[-1]
    by_steps = ["train", str(tmp_path / "steps"), "--preset", "smoke", "--oracle", "--steps", "30",
                "--method", "baseline"]  # fmt: skip
    steps = CliRunner().invoke(app, by_steps)
    assert steps.exit_code == 0, steps.output
    assert re.search(r": 30/30 steps \(100%\)", steps.output), steps.output


def test_evaluate_uses_the_default_its_help_states_and_prints_intervals_as_brackets(tmp_path):
    """`imagine evaluate` without --episodes runs the run's eval_episodes (smoke: 200), as its
    help says; intervals print as [low, high], never low-high (a minus sign reads as a range);
    an AUROC without both wrong and right imagined states prints as n/a with the reason."""
    import math
    import re

    from typer.testing import CliRunner

    from imagine.cli import app, auroc_text

    helped = CliRunner().invoke(app, ["evaluate", "--help"], env={"COLUMNS": "200"})
    assert "default: the run's eval_episodes, 1000; 200 with the smoke preset" in helped.output
    run = tmp_path / "run"
    trained = CliRunner().invoke(app, ["train", str(run), "--preset", "smoke", "--oracle",
                                       "--method", "baseline", "--episodes", "10"])  # fmt: skip
    assert trained.exit_code == 0, trained.output
    done = CliRunner().invoke(app, ["evaluate", str(run)])
    assert done.exit_code == 0, done.output
    assert re.search(r"success \d+\.\d% \(95% CI \[\d+\.\d, \d+\.\d\]%\), 200 episodes; mean "
                     r"return -?\d+\.\d\d \(95% CI \[-?\d+\.\d\d, -?\d+\.\d\d\]\)",
                     done.output), done.output  # fmt: skip
    assert auroc_text(0.8123, 0.5) == "AUROC 0.812"
    assert auroc_text(math.nan, 1.0).startswith("AUROC n/a (every imagined state was right")
    assert auroc_text(math.nan, 0.0).startswith("AUROC n/a (every imagined state was wrong")


def test_a_finished_run_run_again_says_so_and_trains_nothing(tmp_path):
    """The same `imagine train` again on a finished run: one line saying it is finished,
    nothing trained or rewritten; a larger budget trains on."""
    from typer.testing import CliRunner

    from imagine.cli import app
    from imagine.learning.agent import load_agent

    run = tmp_path / "run"
    args = ["train", str(run), "--preset", "smoke", "--oracle", "--method", "baseline"]
    first = CliRunner().invoke(app, [*args, "--episodes", "10"])
    assert first.exit_code == 0, first.output
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir() if p.is_file()}
    again = CliRunner().invoke(app, [*args, "--episodes", "10"])
    assert again.exit_code == 0, again.output
    assert f"{run} is finished (10 episodes, " in again.output
    assert "nothing to train" in again.output and "trained" not in again.output
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir() if p.is_file()} == before
    more = CliRunner().invoke(app, [*args, "--episodes", "12"])
    assert more.exit_code == 0 and "is finished" not in more.output, more.output
    assert load_agent(run).episode == 12
