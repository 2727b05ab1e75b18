"""Algorithm 1 end to end (oracle encoder): it learns, it resumes, it rejects bad settings."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from imagine.config import agent_preset, check_imagines, for_method
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.envs.gesture_puzzle.evaluation import greedy_success, mean_interval, wilson_interval
from imagine.envs.gesture_puzzle.rules import REWARD_GOAL
from imagine.envs.gesture_puzzle.vector import GesturePuzzleVectorEnv
from imagine.errors import CheckpointError, ConfigError
from imagine.learning.agent import load_agent
from imagine.learning.population import Population
from imagine.learning.training import train
from imagine.metrics import read_metrics

IMAGINE = str(Path(sys.executable).parent / "imagine")


def random_agent_success(task: str, episodes: int = 2000) -> float:
    envs = GesturePuzzleVectorEnv(episodes, task=task, autoreset_mode="SameStep")
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    running = np.ones(episodes, dtype=bool)
    success = np.zeros(episodes, dtype=bool)
    while running.any():
        _, reward, terminated, truncated, _ = envs.step(rng.integers(0, 6, episodes))
        success |= running & (reward == REWARD_GOAL)
        running &= ~(terminated | truncated)
    return float(success.mean())


@pytest.mark.parametrize(
    "matmul_dtype", ["float32", pytest.param("bfloat16", marks=pytest.mark.slow)]
)
def test_smoke_agent_with_the_oracle_learns_well_above_random(tmp_path, matmul_dtype):
    """Q-learning (and M) with bfloat16 products learns as with float32 (issue 18)."""
    torch.manual_seed(0)
    config = agent_preset("smoke", encoder="oracle", method="augmented", matmul_dtype=matmul_dtype)
    agent = train(config, tmp_path, threads=1)
    result = greedy_success(agent.controller, agent.encoder, "original", 1000, seed=123)
    random = random_agent_success("original")
    assert 0.02 < random < 0.06  # the paper's random agent: 3.72%
    assert result["success"] > 2.5 * random, (result, random)
    rows = read_metrics(tmp_path / "metrics.csv")
    assert rows[-1]["step"] == 300 and "model/transition_accuracy" in rows[-1]
    assert rows[-1]["charts/imagined_transitions"] > 0  # imagination from I_start on
    assert "charts/imagined_transitions" in rows[0] and rows[0]["charts/imagined_transitions"] == 0


def test_stopped_and_resumed_continues_where_it_was(tmp_path):
    settings = {"encoder": "oracle", "method": "augmented", "imagination_start": 40,
                "checkpoint_every": 50, "log_every": 25, "accuracy_every": 50}  # fmt: skip
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    train(agent_preset("smoke", episodes=120, **settings), straight, threads=1)
    train(agent_preset("smoke", episodes=50, **settings), resumed, threads=1)
    train(agent_preset("smoke", episodes=120, **settings), resumed, threads=1)
    a, b = load_agent(straight), load_agent(resumed)
    assert a.episode == b.episode == 120 and a.t == b.t
    for (name, p), q in zip(a.controller.state_dict().items(), b.controller.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(p, q), name
    for (name, p), q in zip(
        a.model.state_dict().items(), b.model.state_dict().values(), strict=True
    ):
        assert torch.equal(p, q), name

    def numbers(folder):
        return [{k: v for k, v in row.items() if not k.startswith("time")}
                for row in read_metrics(folder / "metrics.csv")]  # fmt: skip

    assert numbers(straight) == numbers(resumed)


def test_bad_agent_configs():
    with pytest.raises(ConfigError, match="beyond the episode budget") as error:
        check_imagines(agent_preset("fast", episodes=500, imagination_start=1000))
    assert "(--episodes 2000 works)" in str(error.value)  # which budget would work
    assert "(--set imagination_start=250)" in str(error.value)  # or which I_start
    for fixed in (dict(episodes=2000), dict(episodes=500, imagination_start=250)):  # they do
        check_imagines(agent_preset("fast", **{"imagination_start": 1000, **fixed}))
    check_imagines(agent_preset("fast", episodes=500, imagination_start=1000, method="baseline"))
    with pytest.raises(ConfigError, match=r"agent\.method must be one of"):
        agent_preset("fast", method="dyna")
    with pytest.raises(ConfigError, match="did you mean 'imagination_depth'"):
        agent_preset("fast", imagination_dept=5)
    with pytest.raises(ConfigError, match=r"must fit in agent\.real_memory"):
        agent_preset("fast", real_memory=100)


def test_a_folder_with_another_run_is_not_overwritten(tmp_path):
    train(agent_preset("smoke", encoder="oracle", episodes=20, method="baseline"), tmp_path,
          threads=1)  # fmt: skip
    with pytest.raises(CheckpointError, match=r"another config \(seed 0 -> 1\)"):
        train(agent_preset("smoke", encoder="oracle", episodes=20, method="baseline", seed=1),
              tmp_path, threads=1)  # fmt: skip
    changed = agent_preset("smoke", encoder="oracle", episodes=30, method="baseline", gamma=0.9,
                           dropout=0.25)  # fmt: skip
    base = agent_preset("smoke")
    named = f"(gamma {base.gamma} -> 0.9, dropout {base.dropout} -> 0.25)"  # field order
    with pytest.raises(CheckpointError) as error:  # every field that differs, old -> new
        train(changed, tmp_path, threads=1)
    assert named in str(error.value) and "episodes" not in str(error.value)


def test_wilson_interval():
    low, high = wilson_interval(500, 1000)
    assert low == pytest.approx(0.469, abs=1e-3) and high == pytest.approx(0.531, abs=1e-3)
    assert wilson_interval(0, 1000)[0] == pytest.approx(0.0, abs=1e-12)


def test_mean_interval_of_returns():
    returns = np.array([50.0, -1.0] * 500)  # mean 24.5, std 25.51
    low, high = mean_interval(returns)
    assert low == pytest.approx(24.5 - 1.96 * 25.5128 / 1000**0.5, abs=1e-3)
    assert high - 24.5 == pytest.approx(24.5 - low)
    assert mean_interval(np.array([3.0])) == (3.0, 3.0)


def test_train_and_evaluate_commands(tmp_path):
    run = tmp_path / "run"
    (tmp_path / "c.yaml").write_text("gamma: 0.9\n")
    done = subprocess.run([IMAGINE, "train", str(run), "--preset", "smoke", "--oracle",
                           "--method", "augmented", "--episodes", "40",
                           "--config", str(tmp_path / "c.yaml"), "--set", "dropout=0.25",
                           "--set", "imagination_start=20"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = subprocess.run([IMAGINE, "evaluate", str(run), "--episodes", "100"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "success" in done.stdout and "M accuracy: transition" in done.stdout
    assert "mean return" in done.stdout
    assert "imagined transitions (sample, as in training" in done.stdout
    assert "the same M with imagination_draw=mode" in done.stdout
    written = json.loads((run / "evaluation.json").read_text())
    assert 0 <= written["imagined_accuracy_mode"]["state"] <= 1
    assert written["return_ci_low"] <= written["mean_return"] <= written["return_ci_high"]
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["gamma"] == 0.9 and saved["dropout"] == 0.25
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "pop"), "--preset", "smoke",
                           "--oracle", "--episodes", "30", "--seeds", "3,1",
                           "--set", "imagination_start=10"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    for s in (1, 3):
        assert load_agent(tmp_path / "pop" / f"seed-{s}").config.seed == s
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "set"), "--preset", "smoke",
                           "--set", "encoder=oracle", "--set", "task=hard", "--episodes", "30",
                           "--set", "imagination_start=10", "--seeds", "0-1"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr  # --set's fields are not overridden by defaults
    for s in (0, 1):
        saved = yaml.safe_load((tmp_path / "set" / f"seed-{s}" / "config.yaml").read_text())
        assert (saved["encoder"], saved["task"], saved["seed"]) == ("oracle", "hard", s)
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "pop"), "--seeds", "1,x"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 2 and "--seeds expects comma-separated integers" in done.stderr
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "x"), "--preset", "smoke"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 2 and "no V run was given" in done.stderr


def test_an_agent_trains_and_is_evaluated_with_a_stochastic_human(tmp_path):
    """hand_switch_prob reaches the training env, the test episodes and M's accuracy, which
    then counts a draw with a moved hand as possible and says how often M keeps the hand."""
    run = tmp_path / "stochastic"
    done = subprocess.run([IMAGINE, "train", str(run), "--preset", "smoke", "--oracle",
                           "--episodes", "60", "--set", "imagination_start=30",
                           "--set", "hand_switch_prob=0.3"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = subprocess.run([IMAGINE, "evaluate", str(run), "--episodes", "200"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (
        "stochastic human: M's draws keep the hand" in done.stdout and "truth 70.0%" in done.stdout
    )
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert 0.0 <= evaluation["model_accuracy"]["hand_kept_sampled"] <= 1.0
    assert 0.0 <= evaluation["hand_calibration"]["total_variation"] <= 1.0
    assert evaluation["hand_calibration_all"]["transitions"] == 192 * 6
    assert load_agent(run).config.hand_switch_prob == 0.3
    with pytest.raises(ConfigError, match="hand_switch_prob"):
        agent_preset("smoke", hand_switch_prob=1.5)


def test_hand_calibration_is_zero_for_an_m_with_the_true_probabilities():
    """An M whose three components sit on the kept and the two moved next states, weighted
    1 - p, p / 2, p / 2, is calibrated; one that always keeps the hand is off by p."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.envs.gesture_puzzle.evaluation import hand_calibration
    from imagine.envs.gesture_puzzle.rules import apply_actions, macrostate_index
    from imagine.models.world_model import Mixture

    encoder, p = OracleEncoder(), 0.3
    latents = encoder.state_latents()

    class TrueMDN(torch.nn.Module):
        def __init__(self, weights):
            super().__init__()
            self.weights = torch.tensor(weights)

        def forward(self, z, action):
            now = encoder.classify(z).numpy()
            rotated = apply_actions(now, action.numpy())
            means = []
            for shift in (0, 1, 2):
                moved = rotated.copy()
                moved[:, 3] = (moved[:, 3] + shift) % 3
                means.append(latents[torch.as_tensor(macrostate_index(moved))])
            mu = torch.stack(means, 1)
            return Mixture(self.weights.log().expand(len(z), 3), mu, torch.full_like(mu, 0.01))

    class StubM(torch.nn.Module):
        def __init__(self, weights):
            super().__init__()
            self.mdn = TrueMDN(weights)

    calibrated = hand_calibration(StubM([1 - p, p / 2, p / 2]), encoder, "hard", p)
    assert abs(calibrated["kept"] - 0.7) < 1e-6 and abs(calibrated["moved_next"] - 0.15) < 1e-6
    assert calibrated["wrong"] < 1e-6 and calibrated["total_variation"] < 1e-6
    stubborn = hand_calibration(StubM([1.0, 1e-9, 1e-9]), encoder, "hard", p)
    assert abs(stubborn["total_variation"] - p) < 1e-6
    everywhere = hand_calibration(StubM([1 - p, p / 2, p / 2]), encoder, "hard", p, True)
    assert everywhere["total_variation"] < 1e-6  # from terminal states too
    assert (calibrated["transitions"], everywhere["transitions"]) == (396, 192 * 6)


def test_a_new_task_starts_from_a_trained_runs_dynamics(tmp_path):
    """init_from (reward transfer, issue 16): the MDN is the source run's, r, d and C fresh;
    a baseline source or another encoder is refused in one line."""
    from imagine.envs.gesture_puzzle.encoders import OracleEncoder
    from imagine.learning.agent_checkpoint import start_dynamics
    from imagine.learning.population import Population, new_networks
    from imagine.learning.training import dynamics_source

    source = tmp_path / "original"
    config = agent_preset("smoke", encoder="oracle", episodes=30, imagination_start=10)
    train(config, source, threads=1)
    hard = dataclasses.replace(config, task="hard", init_from=str(source), seed=3)
    population = Population([hard], OracleEncoder())
    start_dynamics(population, 0, dynamics_source(hard))
    _, model = population.networks(0)
    trained, fresh = load_agent(source).model, new_networks(hard, 8, 6)[1]
    for mine, theirs in zip(
        model.mdn.state_dict().values(), trained.mdn.state_dict().values(), strict=True
    ):
        assert torch.equal(mine, theirs)
    for mine, new in zip(
        model.reward.state_dict().values(), fresh.reward.state_dict().values(), strict=True
    ):
        assert torch.equal(mine, new)
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "hard"), "--task", "hard",
                           "--init-from", str(source), "--preset", "smoke", "--oracle",
                           "--episodes", "20", "--set", "imagination_start=10"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    base = tmp_path / "base"
    train(dataclasses.replace(config, method="baseline", episodes=5), base, threads=1)
    with pytest.raises(ConfigError, match="baseline run"):
        dynamics_source(dataclasses.replace(hard, init_from=str(base)))
    done = subprocess.run([IMAGINE, "train", str(tmp_path / "x"), "--init-from",
                           str(tmp_path / "none"), "--preset", "smoke", "--oracle",
                           "--episodes", "40", "--set", "imagination_start=20"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 2 and "holds no agent run" in done.stderr, done.stderr
    with pytest.raises(ConfigError, match="encoder"):
        dynamics_source(dataclasses.replace(hard, encoder="vae", vae_run="somewhere"))
    with pytest.raises(ConfigError, match=r"init_from: .* has n_components"):  # another M
        dynamics_source(dataclasses.replace(hard, n_components=3))


def test_an_agent_acts_on_camera_images(tmp_path):
    """Agent.load(RUN).act: C's greedy actions for one image or a batch, the same the test
    episodes take; epsilon-greedy from a given generator; the oracle needs macrostates."""
    from imagine.learning.agent import Agent, greedy_actions

    config = agent_preset("smoke", encoder="oracle", method="baseline", episodes=20)
    train(config, tmp_path, threads=1)
    agent = Agent.load(tmp_path)
    envs = GesturePuzzleVectorEnv(8, task="original")
    obs, info = envs.reset(seed=0)
    actions = agent.act(obs, info["macrostate"])
    assert actions.shape == (8,) and actions.dtype == np.int64
    assert np.array_equal(
        actions, greedy_actions(agent.controller, agent.encoder, obs, info["macrostate"])
    )
    assert agent.act(obs[3], info["macrostate"][3]) == actions[3]
    explored = agent.act(np.repeat(obs, 50, 0), np.repeat(info["macrostate"], 50, 0), epsilon=1.0,
                         rng=np.random.default_rng(0))  # fmt: skip
    assert set(explored.tolist()) == set(range(6))
    with pytest.raises(ConfigError, match="pass macrostates"):
        agent.act(obs)


def test_a_saved_agent_carries_v_and_loads_after_v_is_moved_or_deleted(tmp_path):
    """Agent.save writes V (safetensors and JSON, its classifier too) beside C and M: the
    saved folder loads and acts the same after V's run folder is moved and then deleted, and
    after the saved folder itself is moved; nothing in it is a pickle."""
    import shutil

    from imagine.config import vision_preset
    from imagine.learning.agent import Agent
    from imagine.models.vision_training import train_vae

    train_vae(vision_preset("smoke"), tmp_path / "v")
    config = agent_preset("smoke", vae_run=str(tmp_path / "v"), method="augmented", episodes=3,
                          imagination_start=2)  # fmt: skip
    train(config, tmp_path / "run", threads=1)
    agent = Agent.load(tmp_path / "run")
    envs = GesturePuzzleVectorEnv(8, task="original")
    obs, _ = envs.reset(seed=0)
    actions = agent.act(obs)
    mu, _ = agent.encoder.encode(obs, None)
    saved = agent.save(tmp_path / "saved")
    assert {p.name for p in (saved / "vae").iterdir()} == {
        "vae.safetensors", "vae.json", "classifier.safetensors"}  # fmt: skip
    shutil.move(tmp_path / "v", tmp_path / "v-moved")
    again = Agent.load(saved)
    assert np.array_equal(again.act(obs), actions)
    assert torch.equal(again.encoder.encode(obs, None)[0], mu)
    assert torch.equal(again.encoder.state_latents(), agent.encoder.state_latents())
    shutil.rmtree(tmp_path / "v-moved")
    shutil.move(saved, tmp_path / "elsewhere")
    moved = Agent.load(tmp_path / "elsewhere")
    assert np.array_equal(moved.act(obs), actions) and moved.episode == 3
    expected = r"uint8 images of shape \(64, 64, 3\) \(one\) or \(N, 64, 64, 3\) \(a batch\)"
    with pytest.raises(ValueError, match=expected + r"; got float32 of shape \(64, 64, 3\)$"):
        moved.act(obs[0].astype(np.float32) / 255)  # the shape given, not a batched one
    assert len(repr(moved)) < 120 and "memory" not in repr(moved)
    assert Path(moved.config.vae_run) == tmp_path / "elsewhere" / "vae"
    resaved = moved.save(tmp_path / "resaved")  # a loaded saved agent saves again
    assert np.array_equal(Agent.load(resaved).act(obs), actions)
    assert all(p.suffix in (".json", ".safetensors") for p in resaved.rglob("*") if p.is_file())
    with pytest.raises(CheckpointError, match="does not exist"):  # a training run refers to V
        Agent.load(tmp_path / "run")


def test_the_fast_augmented_agent_trusts_an_ensemble_and_the_baseline_has_none():
    """The fast preset's augmented M is an ensemble of 5 behind the mask gate (issue 15, round
    19); its baseline, imagination's control and the paper preset have one M and no gate."""
    fast = agent_preset("fast")
    assert (fast.model_ensemble, fast.imagination_gate, fast.imagination_adaptive) == (
        5, "mask", False)  # fmt: skip
    control = agent_preset("fast", method="baseline", real_in_place_of_imagined=True)
    for config in (agent_preset("fast", method="baseline"), agent_preset("paper"), control):
        assert (config.model_ensemble, config.imagination_gate) == (1, "none")
    given = agent_preset("fast", method="baseline", baseline_trains_m=True, model_ensemble=3)
    assert given.model_ensemble == 3  # given explicitly, the baseline's M takes it


def test_the_fast_augmented_c_has_a_target_network_and_the_baseline_the_papers_c():
    """The fast preset's augmented C bootstraps from a target network copied every 100 updates
    (issue 14, round 18); its baseline and the paper preset keep the paper's C, unless a study
    gives the field to every method."""
    augmented = agent_preset("fast", encoder="oracle")
    baseline = agent_preset("fast", encoder="oracle", method="baseline")
    assert (augmented.target_update_period, baseline.target_update_period) == (100, 0)
    assert agent_preset("paper").target_update_period == 0
    given = for_method({"target_update_period": 100}, "baseline")
    assert agent_preset("fast", method="baseline", **given).target_update_period == 100
    control = agent_preset("fast", method="baseline", real_in_place_of_imagined=True)
    assert (control.target_update_period, control.value_expansion) == (100, 0)  # C, not M
    assert Population([baseline], OracleEncoder()).controller.target is None
    population = Population([augmented], OracleEncoder())
    c = population.controller
    while int(c.updates[0]) < 100:
        population.step()
    assert int(c.updates[0]) == 100  # one real C update a step before I_start (episode 100)
    target = [t[0].clone() for t in c.target.parameters()]
    online = [q[0] for q in c.q.parameters()]
    assert all(map(torch.equal, target, online))  # copied at its 100th update
    population.step()
    assert all(map(torch.equal, target, [t[0] for t in c.target.parameters()]))  # held
    assert not all(map(torch.equal, target, [q[0] for q in c.q.parameters()]))  # C moved on
