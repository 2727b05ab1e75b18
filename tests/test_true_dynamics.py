"""The oracle M of the vector environments (issue 57): CartPole-v1's and Acrobot-v1's own
dynamics, set to an imagined state and stepped, give the real environment's next state,
reward and end; an augmented agent imagines with them in place of its learned M."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from imagine.config import agent_preset
from imagine.envs.classic_control.true_model import TRUE_MODELS
from imagine.errors import ConfigError
from imagine.learning.training import train_population


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Acrobot-v1"])
def test_the_true_model_steps_as_the_environment_does(env_id):
    model = TRUE_MODELS[env_id]()
    env = gym.make(env_id)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=3)
    states, actions, nexts, rewards, ends = [], [], [], [], []
    while len(states) < 300:  # several episodes, their terminal steps included
        a = int(rng.integers(env.action_space.n))
        nxt, r, terminated, truncated, _ = env.step(a)
        states.append(obs), actions.append(a), nexts.append(nxt)
        rewards.append(r), ends.append(terminated)
        obs = env.reset()[0] if terminated or truncated else nxt
    z = torch.as_tensor(np.array(states), dtype=torch.float32)[None]  # (1, N, D)
    prediction = model.predict(z, torch.as_tensor(actions)[None])
    # the observation is float32, so the state set from it is within float32 rounding
    np.testing.assert_allclose(prediction.next_z[0].numpy(), np.array(nexts), atol=1e-4)
    truth = torch.as_tensor(np.array(nexts), dtype=torch.float32)[None]
    assert model.is_terminal(truth)[0].tolist() == ends
    assert model.predict_reward(truth)[0].tolist() == rewards
    if env_id == "CartPole-v1":  # Acrobot's ends: the test below
        assert sum(ends) >= 3


def test_an_agent_imagines_with_cartpoles_own_dynamics(tmp_path):
    config = agent_preset("smoke", env="CartPole-v1", encoder="vector", method="augmented",
                          episodes=10**6, steps=300, imagination_start=3,
                          imagination_model="true")  # fmt: skip
    agent = train_population([config], [tmp_path / "run"], threads=1).agents[0]
    assert agent.t == 300
    rows = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    imagined = rows[0].split(",").index("charts/imagined_transitions")
    assert float(rows[-1].split(",")[imagined]) > 0
    with pytest.raises(ConfigError, match="learned or true"):
        train_population([agent_preset("smoke", env="CartPole-v1", encoder="vector",
                                       method="augmented", steps=50, imagination_start=1,
                                       imagination_model="true_end")],
                         [tmp_path / "other"], threads=1)  # fmt: skip


def test_the_probe_scores_m_on_held_out_transitions(tmp_path):
    """A CartPole agent's metrics carry M's probe every accuracy_every episodes, each score a
    share; an untrained M's next states are not close to the truth."""
    from imagine.envs.classic_control.extras import model_probe
    from imagine.metrics import read_metrics
    from imagine.models.world_model import WorldModel

    config = agent_preset("smoke", env="CartPole-v1", encoder="vector", method="augmented",
                          episodes=10**6, steps=400, imagination_start=3,
                          accuracy_every=5)  # fmt: skip
    train_population([config], [tmp_path / "run"], threads=1)
    rows = read_metrics(tmp_path / "run" / "metrics.csv")
    logged = [r for r in rows if r.get("model/next_state_accuracy") not in (None, "")]
    assert logged, "the probe is logged every accuracy_every episodes"
    keys = ("next_state", "terminal", "nonterminal", "reward")
    assert all(0.0 <= float(logged[-1][f"model/{k}_accuracy"]) <= 1.0 for k in keys)
    torch.manual_seed(0)
    untrained = model_probe(WorldModel(4, 2), None, config)
    assert untrained["next_state"] < 0.5


def test_acrobots_end_and_reward_match_the_environments_own_rule():
    """Random play rarely ends Acrobot-v1, so its terminal rule is checked on states built
    for it: the tip above the bar (t1 = pi), below it (t1 = 0) and near the line."""
    model = TRUE_MODELS["Acrobot-v1"]()
    angles = [(np.pi, 0.0), (0.0, 0.0), (2.2, 0.4), (2.0, 0.1), (np.pi / 2, 0.0), (3.0, -2.0)]
    obs = np.array([[np.cos(a), np.sin(a), np.cos(b), np.sin(b), 0.0, 0.0] for a, b in angles])
    truth = []
    for a, b in angles:
        model.env.state = np.array([a, b, 0.0, 0.0])
        truth.append(bool(model.env._terminal()))
    assert model.terminal(obs).tolist() == truth
    assert truth[0] and not truth[1] and len(set(truth)) == 2
    assert model.reward(obs).tolist() == [0.0 if t else -1.0 for t in truth]


def test_set_reads_the_oracle_choice_true_as_text():
    """`--set imagination_model=true` names the oracle (a str field keeps its text), where
    YAML alone would read a boolean; other values are still read as YAML."""
    from imagine.config import parse_assignments

    got = parse_assignments(["imagination_model=true", "gamma=0.9", "vae_run=null"])
    assert got == {"imagination_model": "true", "gamma": 0.9, "vae_run": None}
    assert agent_preset("fast", **got).imagination_model == "true"
