"""`imagine bench`: the sample-efficiency suite (issue 57). Every arm of ours trains on a toy
environment and seed to each budget, the replay-ratio control gets the augmented agent's C
updates per step, the report judges imagination only from enough seeds, a rerun trains
nothing, and a bad suite file is a one-line error."""

import dataclasses
import json

import pytest
import yaml
from typer.testing import CliRunner

import toy_envs  # noqa: F401  (registers imagine-test/*)
from imagine.cli import app
from imagine.errors import ConfigError
from imagine.study.suite import arm_config, load_suite, steps_to_match, verdicts

LINE = "toy_envs:imagine-test/Line-v0"  # importable in a spawned worker too


def suite_file(tmp_path, **overrides):
    suite = {"seeds": "0,1", "episodes": 10, "arms": ["baseline", "control", "augmented"],
             "environments": [{"env": LINE, "budgets": [30, 60], "reference": 1.0,
                               "reference_source": "the goal's reward", "preset": "fast",
                               "set": {"gamma": 0.9, "imagination_start": 2,
                                       "imagination_depth": 2, "model_ensemble": 2}}]}  # fmt: skip
    suite |= overrides
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite))
    return path


def test_the_control_makes_as_many_c_updates_as_the_augmented_agent(tmp_path):
    entry = load_suite(suite_file(tmp_path)).environments[0]
    baseline, control, augmented = (arm_config(entry, a)
                                    for a in ("baseline", "control", "augmented"))  # fmt: skip
    assert (baseline.method, control.method, augmented.method) == ("baseline",) * 2 + ("augmented",)
    assert control.real_in_place_of_imagined and not baseline.real_in_place_of_imagined
    # as many C updates a step, from the same I_start, and the augmented agent's target net
    assert control.n_imaginary_updates == augmented.n_imaginary_updates == 3
    assert control.imagination_start == augmented.imagination_start == 2
    assert control.target_update_period == augmented.target_update_period == 100
    assert baseline.target_update_period != 100
    assert augmented.model_ensemble == 2 and augmented.gamma == control.gamma == 0.9


def test_bench_trains_every_arm_reports_and_resumes(tmp_path):
    path = suite_file(tmp_path)
    out = tmp_path / "out"
    partial = CliRunner().invoke(app, ["bench", str(path), str(out), "--up-to", "30"])
    assert partial.exit_code == 0, partial.output
    assert "| 30 | augmented | 2 |" in (out / "SUITE.md").read_text()
    assert "| 60 |" not in (out / "SUITE.md").read_text()
    done = CliRunner().invoke(app, ["bench", str(path), str(out), "--workers", "2"])
    assert done.exit_code == 0, done.output
    folder = out / "toy_envs-imagine-test-Line-v0"
    report = (out / "SUITE.md").read_text()
    for steps in (30, 60):
        for arm in ("baseline", "control", "augmented"):
            assert f"| {steps} | {arm} | 2 |" in report
    assert "no claim (2 seeds)" in report and "| yes |" not in report
    assert (folder / "comparison.png").stat().st_size > 0
    assert json.loads((folder / "random.json").read_text())["episodes"] == 10
    record = json.loads((folder / "control" / "seed-1" / "evaluation-0000060.json").read_text())
    assert record["method"] == "control" and record["config"]["real_in_place_of_imagined"]
    assert record["commit"] and record["config"]["steps"] == 60
    assert record["nudge_epsilon"] == 0.001 and "nudged_mean_return" in record
    assert 0.0 <= record["truncated"] <= 1.0
    assert "mean at epsilon 0.001" in report
    metrics = (folder / "control" / "seed-1" / "metrics.csv").read_text().splitlines()[0]
    assert "losses/controller_real_extra" in metrics  # the control's extra real updates
    before = record["commit"], (folder / "control" / "seed-1" / "evaluation-0000060.json")
    mtime = before[1].stat().st_mtime_ns
    again = CliRunner().invoke(app, ["bench", str(path), str(out), "--workers", "1"])
    assert again.exit_code == 0 and before[1].stat().st_mtime_ns == mtime


def test_verdicts_judge_against_the_stronger_baseline():
    def row(method, steps, iqm, low, high, mean=None, n=5):
        return {"method": method, "steps": steps, "n": n, "iqm": iqm, "iqm_low": low,
                "iqm_high": high, "mean": iqm if mean is None else mean}  # fmt: skip

    rows = [row("baseline", 10, 5, 4, 6), row("control", 10, 8, 7, 9),
            row("augmented", 10, 3, 2, 3.5),  # below the control: hurts
            row("baseline", 20, 5, 4, 6), row("control", 20, 6, 5, 7),
            row("augmented", 20, 9, 8, 10),  # above both: pays
            row("baseline", 40, 9, 8, 10), row("control", 40, 7, 6, 8),
            row("augmented", 40, 9.5, 7.5, 11)]  # fmt: skip
    got = {v["steps"]: v for v in verdicts(rows)}
    assert (got[10]["stronger"], got[10]["hurts"], got[10]["pays"]) == ("control", True, False)
    assert (got[20]["hurts"], got[20]["pays"]) == (False, True)
    assert (got[40]["stronger"], got[40]["hurts"], got[40]["pays"]) == ("baseline", False, False)
    assert all(v["judged"] for v in got.values())
    # the stronger baseline's mean at 40 steps (9) is first reached at 20 steps
    assert steps_to_match(rows) == (40, 20)
    assert steps_to_match([{**r, "n": 2} for r in rows]) == (None, None)  # too few seeds
    # a budget one baseline has not reached is not the bar
    assert steps_to_match([r for r in rows if (r["method"], r["steps"]) != ("control", 40)]) == (
        20,
        20,
    )
    few = verdicts([{**r, "n": 2} for r in rows])
    assert not any(v["judged"] for v in few)


@pytest.mark.parametrize(
    "change, message",
    [({"arms": ["baseline", "dreamer"]}, "arms is a list"),
     ({"arms": "baseline"}, "arms is a list"),
     ({"arms": [{"a": 1}]}, "arms is a list"),
     ({"episodes": True}, "episodes must be"),
     ({"seeds": "0-x"}, "seeds is e.g."),
     ({"environments": [{"env": LINE, "budgets": [10], "reference": 1,
                         "reference_source": "x"}] * 2}, "share one folder"),
     ({"environments": []}, "non-empty list"),
     ({"seed": 3}, "unknown key 'seed'"),
     ({"environments": [{"env": LINE, "budgets": [10]}]}, "needs 'reference'"),
     ({"environments": [{"env": LINE, "budgets": [0], "reference": 1,
                         "reference_source": "x"}]}, "positive step counts")],
)  # fmt: skip
def test_a_bad_suite_file_is_a_one_line_error(tmp_path, change, message):
    path = suite_file(tmp_path, **change)
    with pytest.raises(ConfigError, match=message):
        load_suite(path)
    done = CliRunner().invoke(app, ["bench", str(path), str(tmp_path / "out")])
    assert done.exit_code != 0 and message in str(done.exception)


def test_the_shipped_suite_resolves():
    """suites/sample-efficiency.yaml: every arm's config of every environment resolves."""
    from pathlib import Path

    from imagine.study.suite import check_suite

    suite = load_suite(Path(__file__).parent.parent / "suites" / "sample-efficiency.yaml")
    assert {"CartPole-v1", "Acrobot-v1"} <= {e.env for e in suite.environments}
    assert suite.seeds == (0, 1, 2, 3, 4)
    check_suite(suite)


def test_seeds_as_a_list_and_a_changed_setting_refused_on_resume(tmp_path):
    """seeds may be a YAML list; a rerun with another setting over finished evaluations is a
    one-line error naming the field, not a reuse of results it did not ask for."""
    assert load_suite(suite_file(tmp_path, seeds=[0, 2])).seeds == (0, 2)
    out = tmp_path / "out"
    path = suite_file(tmp_path, seeds="0", arms=["baseline"])
    assert CliRunner().invoke(app, ["bench", str(path), str(out), "--up-to", "30"]).exit_code == 0
    raw = yaml.safe_load(path.read_text())
    raw["environments"][0]["set"]["gamma"] = 0.8
    path.write_text(yaml.safe_dump(raw))
    again = CliRunner().invoke(app, ["bench", str(path), str(out), "--up-to", "30"])
    assert again.exit_code != 0 and "gamma 0.9 -> 0.8" in str(again.exception)


def test_a_record_older_than_a_field_is_reused_only_where_the_field_keeps_its_default(tmp_path):
    from imagine.checkpoint import write_json
    from imagine.config import agent_preset
    from imagine.study.compare import check_evaluation

    config = agent_preset("fast", method="baseline", env="CartPole-v1", encoder="vector")
    recorded = json.loads(json.dumps(dataclasses.asdict(config)))
    del recorded["imagination_trust_tolerance"]  # a field added after the record was made
    path = tmp_path / "evaluation-0000010.json"
    write_json(path, {"config": recorded, "episodes": 100})
    check_evaluation(path, config, 100)  # the default now is what the record measured
    other = dataclasses.replace(config, imagination_trust_tolerance=0.3)
    with pytest.raises(ConfigError, match=r"imagination_trust_tolerance 0.1 -> 0.3"):
        check_evaluation(path, other, 100)
    with pytest.raises(ConfigError, match=r"gamma 0.99 -> 0.8"):
        check_evaluation(path, dataclasses.replace(config, gamma=0.8), 100)


def test_epsilon_greedy_deviates_at_its_rate_and_passes_restarts_on():
    import numpy as np

    from imagine.learning.test_episodes import EpsilonGreedy

    class Always:
        restarted = None

        def __call__(self, x, extra, copies):
            return np.zeros(len(x), dtype=np.int64)

        def restart(self, copies):
            self.restarted = copies

    inner = Always()
    x = np.zeros((20_000, 2))
    assert not EpsilonGreedy(inner, 4, 0.0, seed=0)(x, None, None).any()
    nudged = EpsilonGreedy(inner, 4, 0.1, seed=0)(x, None, None)
    # a random action replaces the policy's 10% of the time; 3 in 4 of those differ from it
    assert abs((nudged != 0).mean() - 0.075) < 0.01
    EpsilonGreedy(inner, 4, 0.1, seed=0).restart(np.array([3]))
    assert inner.restarted.tolist() == [3]


def test_circling_finds_a_greedy_policy_that_goes_back_and_forth():
    """A policy that alternates left and right on the toy line never reaches the goal: every
    episode runs to the 20-step limit, circling with period 2; one that goes right ends."""
    import numpy as np

    from imagine.envs.spec import gym_spec
    from imagine.learning.test_episodes import circling

    spec = gym_spec("imagine-test/Line-v0", ())

    class BackAndForth:
        def __init__(self):
            self.t = 0

        def __call__(self, x, extra, copies):
            self.t += 1
            return np.array([self.t % 2])  # right, left, right, ...

        def restart(self, copies):
            self.t = 0

    loops = circling(spec, BackAndForth(), episodes=6, seed=0)
    assert loops["truncated"] == 1.0 and loops["circling"] == 1.0
    assert loops["median_period"] == 2 and loops["one_action"] == 0.5
    stay = circling(spec, lambda x, extra, copies: np.array([2]), episodes=3, seed=0)
    assert stay["circling"] == 1.0 and stay["median_period"] == 1  # a fixed point
    assert stay["one_action"] == 1.0
    right = circling(spec, lambda x, extra, copies: np.array([1]), episodes=6, seed=0)
    assert right["truncated"] == 0.0 and right["circling"] == 0.0


def test_an_augmented_agents_evaluation_carries_ms_probe_and_the_report_reads_it():
    from imagine.config import agent_preset
    from imagine.learning.agent import Agent, make_encoder
    from imagine.learning.population import new_networks
    from imagine.study.compare import probed
    from imagine.study.suite import probe_rows

    def agent(method):
        config = agent_preset("fast", env="CartPole-v1", encoder="vector", method=method)
        encoder = make_encoder(config)
        controller, model = new_networks(config, encoder.latent_dim, 2)
        return Agent(config, encoder, controller.eval(), model.eval(), 0, 0)

    assert probed(agent("baseline")) == {}  # no M to probe
    readings = probed(agent("augmented"))["model_probe"]
    assert set(readings) == {"next_state", "terminal", "nonterminal", "reward"}
    assert all(0.0 <= v <= 1.0 for v in readings.values())
    assert readings["next_state"] < 0.5  # an untrained M does not know CartPole's dynamics
    evaluations = [
        {"method": "augmented", "steps": 10, "seed": 0,
         "model_probe": {"next_state": 1.0, "terminal": 0.5, "nonterminal": 1.0, "reward": 1.0}},
        {"method": "augmented", "steps": 10, "seed": 1,
         "model_probe": {"next_state": 0.5, "terminal": None, "nonterminal": 0.9, "reward": 1.0}},
        {"method": "control", "steps": 10, "seed": 0},
    ]  # fmt: skip
    assert probe_rows("E", evaluations) == ["| E | 10 | 2 | 75.0% | 50.0% | 95.0% | 100.0% |"]
