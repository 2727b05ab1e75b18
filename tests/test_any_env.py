"""Algorithm 1 on any Gymnasium environment (issue 17): toy environments registered in the test
suite (tests/toy_envs.py) train end to end, beat a random agent, stop at different times in one
population, resume exactly, and bad environments get one-line errors."""

import dataclasses
import sys

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import imagine
import toy_envs  # noqa: F401  (registers imagine-test/*)
from imagine.config import agent_preset
from imagine.envs.gym import GymSpec
from imagine.envs.spec import make_spec
from imagine.errors import CheckpointError, ConfigError
from imagine.learning.agent import Agent, load_agent
from imagine.learning.extras import EnvExtras, extras_of, register_extras
from imagine.learning.test_episodes import greedy_policy, random_policy, run_episodes
from imagine.learning.training import train_population

LINE = "imagine-test/Line-v0"
LINE_DISCRETE = "imagine-test/LineDiscrete-v0"
LINE_GRID = "imagine-test/LineGrid-v0"  # a 1 x 5 x 2 grid of booleans, as MinAtar's


def toy_config(env=LINE, encoder="vector", **overrides):
    """A small agent for the toy line (gamma 0.9: the paper's C without a target network
    learns this 4-step task reliably with it in a few hundred steps)."""
    values = dict(env=env, encoder=encoder, method="baseline", episodes=10**6, steps=300,
                  gamma=0.9, eps_time="episode", eps_decay=0.1, imagination_start=3,
                  imagination_breadth=1, imagination_depth=3)  # fmt: skip
    return agent_preset("smoke", **{**values, **overrides})


def tensors_equal(a, b):
    x, y = load_file(str(a / "agent.safetensors")), load_file(str(b / "agent.safetensors"))
    return x.keys() == y.keys() and all(bool((x[k] == y[k]).all()) for k in x)


@pytest.mark.parametrize(
    "env, encoder, method",
    [
        (LINE, "vector", "augmented"),
        (LINE_DISCRETE, "onehot", "baseline"),
        (LINE_GRID, "vector", "augmented"),
    ],
)
def test_toy_env_agent_beats_random(tmp_path, env, encoder, method):
    config = toy_config(env, encoder, method=method)
    agent = train_population([config], [tmp_path / "run"], threads=1).agents[0]
    assert agent.t == 300  # the step budget, exactly
    spec = make_spec(config)
    trained = run_episodes(spec, greedy_policy(agent.controller, agent.encoder), 50, seed=7)
    random = run_episodes(spec, random_policy(spec.n_actions, 0), 50, seed=7)
    assert trained["success"] >= 0.9 > random["success"]
    assert trained["mean_return"] > random["mean_return"] + 1.0
    assert agent.controller.n_actions == 3
    loaded = load_agent(tmp_path / "run")  # Agent.act on raw observations
    obs = {LINE: np.array([[0.25, 1.0]], np.float32), LINE_DISCRETE: np.array([1]),
           LINE_GRID: np.zeros((1, 1, 5, 2), bool)}[env]  # fmt: skip
    if env == LINE_GRID:  # at position 1, the goal at 4; flattened: 10 inputs
        obs[0, 0, 1, 0] = obs[0, 0, 4, 1] = True
        assert loaded.encoder.latent_dim == 10 and loaded.encoder.observation_shape == (1, 5, 2)
    assert loaded.act(obs[0]) == loaded.act(obs)[0] == 1  # right, towards the goal
    saved = loaded.save(tmp_path / "saved")  # Agent.save: networks only, loads back the same
    again = Agent.load(saved)
    assert (again.act(obs) == loaded.act(obs)).all() and again.t == agent.t == 300
    assert all(
        again.controller.state_dict()[k].equal(v) for k, v in loaded.controller.state_dict().items()
    )
    with pytest.raises(CheckpointError, match="saved agent"):  # not a run to resume
        train_population([config], [saved], threads=1)
    before = (tmp_path / "run" / "agent.json").read_bytes()
    with pytest.raises(CheckpointError, match="holds a training run"):  # never over a run
        loaded.save(tmp_path / "run")
    assert (tmp_path / "run" / "agent.json").read_bytes() == before


def test_act_on_a_wrong_observation_names_the_expected_and_given_shapes(tmp_path):
    """Agent.act on an observation of another shape is a ValueError naming the shape the
    agent acts on and the one given (not a batched one, nor a raw RuntimeError, nor a silent
    reshape of an 8-vector into two 4-vectors); print(agent) is one short line."""
    from imagine.errors import ObservationError

    train_population([toy_config(steps=30)], [tmp_path / "run"], threads=1)
    agent = load_agent(tmp_path / "run")  # observations (2,)
    assert agent.act(np.zeros(2, np.float32)) in range(3)
    assert agent.act(np.zeros((5, 2))).shape == (5,)
    for wrong in (np.zeros(3), np.zeros(4), np.zeros((5, 3)), np.float32(1.0)):
        with pytest.raises(ValueError, match=r"of shape \(2,\) \(one\) or \(N, 2\)") as error:
            agent.act(wrong)
        assert isinstance(error.value, ObservationError)
        assert str(error.value).endswith(f"got {wrong.dtype} of shape {np.shape(wrong)}")
    shown = repr(agent)
    assert shown == str(agent) == (f"Agent(env={LINE}, method=baseline, encoder=vector, "
                                   f"episodes={agent.episode}, steps=30)")  # fmt: skip
    train_population([toy_config(LINE_DISCRETE, "onehot", steps=30)], [tmp_path / "d"],
                     threads=1)  # fmt: skip
    discrete = load_agent(tmp_path / "d")
    assert discrete.act(np.int64(1)) in range(3) and discrete.act(np.array([0, 1])).shape == (2,)
    with pytest.raises(ObservationError, match=r"integer observations .* got float64"):
        discrete.act(np.array([0.5, 1.0]))


def test_population_agents_stop_apart_and_equal_alone(tmp_path):
    """Two seeds with an episode budget stop at different real steps; the one that stopped
    has its env reset and stepped (a SyncVectorEnv refuses a finished env), and each agent's
    checkpoint is bitwise the one it gets alone, also when resumed halfway."""
    config = toy_config(episodes=12, steps=0)
    configs = [config, dataclasses.replace(config, seed=1)]
    result = train_population(configs, [tmp_path / "p0", tmp_path / "p1"], threads=1)
    assert result.agents[0].t != result.agents[1].t
    train_population([configs[1]], [tmp_path / "alone"], threads=1)
    assert tensors_equal(tmp_path / "p1", tmp_path / "alone")
    half = dataclasses.replace(configs[1], episodes=5)
    train_population([half], [tmp_path / "resumed"], threads=1)
    train_population([configs[1]], [tmp_path / "resumed"], threads=1)
    assert tensors_equal(tmp_path / "resumed", tmp_path / "alone")


def test_test_episodes_do_not_depend_on_copies():
    spec = make_spec(toy_config())

    def right_unless_at_start(x, extra, copies):  # a fixed policy that depends on the observation
        return np.where(x[:, 0] < 0.3, 2, 1)

    one = run_episodes(spec, right_unless_at_start, 20, seed=3, copies=3)
    other = run_episodes(spec, right_unless_at_start, 20, seed=3, copies=20)
    assert one == other
    assert 0 < one["success"] < 1  # position 1 stays forever, position 2 walks to the goal


@pytest.mark.parametrize(
    "env, message",
    [
        ("Pendulum-v1", "needs a Discrete action space"),
        ("imagine-test/NoSuchEnv-v0", "env imagine-test/NoSuchEnv-v0"),
        ("imagine-test/LineTuple-v0", "is not supported"),
    ],
)
def test_bad_environments_one_line(env, message):
    with pytest.raises(ConfigError, match=message) as error:
        GymSpec(env)
    assert "\n" not in str(error.value)


def test_bad_wrapper_and_encoder(tmp_path):
    with pytest.raises(ConfigError, match="module:Class"):
        GymSpec(LINE, ["no_colon"])
    with pytest.raises(ConfigError, match="cannot import"):
        GymSpec(LINE, ["no_such_module_here:Wrapper"])
    with pytest.raises(ConfigError, match=r"set agent\.encoder=onehot"):
        train_population([toy_config(LINE_DISCRETE, "vector")], [tmp_path / "a"], threads=1)
    with pytest.raises(ConfigError, match="own dynamics; imagine-test/Line-v0 has none"):
        config = toy_config(method="augmented", imagination_model="true")
        train_population([config], [tmp_path / "b"], threads=1)


PROBED = []


def line_probe(model, encoder, config):
    """A user's probe of M on the toy line: its most likely next position from the start,
    moving right (the true one: 0.25)."""
    PROBED.append(config.env)
    x = model.eval().mdn.most_likely(torch.tensor([[0.0, 1.0]]), torch.tensor([1]))[0, 0]
    return {"right_from_start": float(abs(x - 0.25) < 0.1)}


LINE_EXTRAS = EnvExtras(model_probe=line_probe)


def test_an_environment_registers_its_own_extras(tmp_path, monkeypatch):
    """A user's environment names its extras by entry point (as GesturePuzzle does): its probe
    of M is logged with the metrics; without extras there is none."""
    monkeypatch.setattr(imagine, "EXTRAS", dict(imagine.EXTRAS))  # this test's registry
    PROBED.clear()
    register_extras(LINE, "test_any_env:LINE_EXTRAS")
    config = toy_config(method="augmented", steps=150, accuracy_every=5, log_every=5)
    train_population([config], [tmp_path / "probed"], threads=1)
    header = (tmp_path / "probed" / "metrics.csv").read_text().splitlines()[0]
    assert "model/right_from_start_accuracy" in header and PROBED == [LINE] * len(PROBED) != []
    register_extras(LINE, "test_any_env:line_probe")
    with pytest.raises(ConfigError, match="is not an EnvExtras"):
        train_population([config], [tmp_path / "bad"], threads=1)
    # an env named module:Id finds the extras its module registers on import (as Gymnasium
    # imports it to find the env), under Id or module:Id
    (tmp_path / "user_env.py").write_text(
        "from imagine.learning.extras import EnvExtras, register_extras\n"
        "EXTRAS = EnvExtras(model_probe=lambda model, encoder, config: {'x': 1.0})\n"
        "register_extras('UserLine-v0', 'user_env:EXTRAS')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "user_env", raising=False)
    assert extras_of("user_env:UserLine-v0").model_probe is not None
    assert extras_of("UserLine-v0").model_probe is not None
    assert extras_of(LINE_DISCRETE).model_probe is None  # an env without extras


def test_wrappers_apply_in_order():
    spec = GymSpec(LINE, ["gymnasium.wrappers:FlattenObservation"])
    assert spec.kind == "vector" and spec.n_actions == 3


def test_image_env_through_v_end_to_end(tmp_path):
    """`imagine vae train --env` fits V on a random policy's frames (8 x 8 images resized to
    64 x 64); `imagine train --env --vae` learns through it and beats random;
    `imagine evaluate` writes the mean return and success."""
    import json

    from typer.testing import CliRunner

    from imagine.cli import app

    env, runner = "imagine-test/LineImage-v0", CliRunner()
    v = tmp_path / "v"
    done = runner.invoke(app, ["vae", "train", "--env", env, "--out", str(v), "--preset", "smoke",
                               "--set", "epochs=1", "--device", "cpu"])  # fmt: skip
    assert done.exit_code == 0, done.output
    assert not (v / "classifier.safetensors").exists()  # macrostates are GesturePuzzle's
    run = tmp_path / "agent"
    done = runner.invoke(app, ["train", str(run), "--env", env, "--vae", str(v), "--steps", "300",
                               "--method", "baseline", "--preset", "smoke", "--set", "gamma=0.9",
                               "--set", "eps_time=episode", "--set", "eps_decay=0.1",
                               "--device", "cpu"])  # fmt: skip
    assert done.exit_code == 0, done.output
    done = runner.invoke(app, ["evaluate", str(run), "--episodes", "50"])
    assert done.exit_code == 0, done.output
    result = json.loads((run / "evaluation.json").read_text())
    spec = make_spec(toy_config(env, "vae"))
    random = run_episodes(spec, random_policy(spec.n_actions, 0), 50, seed=1_000_000)
    assert result["success"] >= 0.9 and result["mean_return"] > random["mean_return"] + 1.0
    import shutil

    agent = load_agent(run)  # a saved agent carries its V: it acts with V's run deleted
    import gymnasium

    frames = np.stack([gymnasium.make(env).reset(seed=s)[0] for s in range(4)])
    saved = agent.save(tmp_path / "saved")
    shutil.rmtree(v)
    assert not (saved / "vae" / "classifier.safetensors").exists()
    assert np.array_equal(Agent.load(saved).act(frames), agent.act(frames))
    wrong = runner.invoke(app, ["train", str(tmp_path / "b"), "--env", LINE, "--vae", str(v),
                                "--set", "encoder=vae", "--steps", "10"])  # fmt: skip
    assert wrong.exit_code != 0 and "vector observations" in str(wrong.exception)


def test_compare_table_and_figure(tmp_path, monkeypatch):
    """`imagine compare`: both our methods at each budget, the same test episodes, a table
    with IQM intervals and a figure; SB3's row skipped in one line when it is not installed;
    a second run reuses every evaluation."""
    from typer.testing import CliRunner

    import imagine.study.compare
    from imagine.cli import app

    monkeypatch.setattr(imagine.study.compare, "sb3_available", lambda: False)
    args = ["compare", "--env", LINE, "--out", str(tmp_path), "--steps", "30,60",
            "--seeds", "0,1", "--episodes", "10", "--preset", "smoke", "--set", "gamma=0.9",
            "--set", "imagination_start=2", "--set", "imagination_depth=2"]  # fmt: skip
    done = CliRunner().invoke(app, args)
    assert done.exit_code == 0, done.output
    assert "sb3-dqn skipped" in done.output
    table = (tmp_path / "comparison.md").read_text()
    for steps in (30, 60):
        for method in ("baseline", "augmented"):
            assert f"| {steps} | {method} | 2 |" in table
    assert (tmp_path / "comparison.png").stat().st_size > 0
    evaluation = tmp_path / "augmented" / "seed-1" / "evaluation-0000060.json"
    before = evaluation.stat().st_mtime_ns
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and evaluation.stat().st_mtime_ns == before


def test_sb3_row_when_installed(tmp_path, monkeypatch):
    pytest.importorskip("stable_baselines3")
    import tempfile

    from imagine.study.compare import gather, train_sb3

    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))
    out = tmp_path / "out"
    train_sb3(LINE, [], out, [0], [150, 300], episodes=10, log=lambda line: None)
    assert not list(temporary.glob("SB3-*"))  # SB3's logger left no folder behind
    rows = gather(out)
    assert [r["steps"] for r in rows] == [150, 300]
    assert all(r["method"] == "sb3-dqn" and not r["rl_zoo"] for r in rows)
    assert rows[0]["settings"] == {"buffer_size": 300}  # SB3's defaults, a buffer of the run


def test_gesture_puzzle_extras_refused_in_one_line(tmp_path):
    """Planning and the generalization test read GesturePuzzle's rules: asked of another
    environment's run they are a one-line error, not a traceback."""
    from typer.testing import CliRunner

    from imagine.cli import app

    config = toy_config(episodes=3, steps=0)
    train_population([config], [tmp_path / "run"], threads=1)
    for command in ("plan", "generalize"):
        done = CliRunner().invoke(app, [command, str(tmp_path / "run")])
        assert done.exit_code != 0 and "is GesturePuzzle's" in str(done.exception)
