"""C's belief (issue 14, round 11): V's observation filtered through M's prediction of it."""

import copy

import numpy as np
import pytest
import torch

from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.errors import ConfigError
from imagine.learning.agent import belief_tracker, greedy_actions, load_agent
from imagine.learning.belief import BeliefTracker, fuse
from imagine.learning.test_episodes import GreedyPolicy
from imagine.learning.training import train
from imagine.models.controller import Controller
from imagine.models.world_model import Mixture, WorldModel, mixture_mode, responsible_mean


def test_the_belief_averages_ms_prediction_and_vs_observation():
    torch.manual_seed(0)
    model = WorldModel(4, n_actions=6, dropout=0.2, residual=True).train()  # dropout: not used
    mdn = model.members[0]
    tracker = BeliefTracker(model, 0.5, n=3, latent_dim=4)
    mu0, mu1, mu2 = torch.randn(3, 4), torch.randn(3, 4), torch.randn(3, 4)
    rows = torch.arange(3)
    assert torch.equal(tracker.observe(mu0, rows), mu0)  # b_0 = mu_0
    a = torch.tensor([0, 3, 5])
    tracker.acted(a, rows)
    two = torch.tensor([0, 2])  # row 1 has ended: only 0 and 2 observe
    b1 = tracker.observe(mu1[two], two)
    assert mdn.training  # the tracker leaves the MDN's mode as it found it
    mdn.eval()
    expected = 0.5 * mdn.explain(mu0[two], a[two], mu1[two]) + 0.5 * mu1[two]
    assert torch.allclose(b1, expected, atol=1e-6)
    tracker.acted(torch.tensor([1, 2]), two)
    tracker.restart(torch.tensor([0]))  # row 0 starts a new episode
    b2 = tracker.observe(mu2[two], two)
    mdn.eval()
    assert torch.equal(b2[0], mu2[0])
    m = mdn.explain(b1[1:], torch.tensor([2]), mu2[2:])  # recursive: from row 2's belief
    assert torch.allclose(b2[1], fuse(m[0], mu2[2], 0.5), atol=1e-6)
    assert torch.equal(BeliefTracker(model, 0.0, 3, 4).observe(mu1, rows), mu1)  # w = 0: mu


def test_the_baseline_and_observation_belief_act_on_vs_means():
    assert agent_preset("fast", method="baseline", belief="filtered").filter_weight == 0.0
    assert agent_preset("smoke", belief="observation").filter_weight == 0.0
    assert agent_preset("smoke", belief="filtered", belief_weight=0.3).filter_weight == 0.3
    for exact in ("vector", "onehot"):  # observations as they are: nothing to filter
        assert agent_preset("smoke", belief="filtered", encoder=exact).filter_weight == 0.0
    with pytest.raises(ConfigError, match="belief_weight must be in"):
        agent_preset("smoke", belief_weight=1.0)
    with pytest.raises(ConfigError, match="belief must be one of"):
        agent_preset("smoke", belief="kalman")


def test_agent_act_keeps_the_belief_between_the_steps_of_an_episode(tmp_path):
    config = agent_preset("smoke", encoder="oracle", episodes=20, imagination_start=5,
                          belief="filtered")  # fmt: skip
    agent = train(config, tmp_path, threads=1)
    states = np.array([[0, 1, 2, 0], [1, 2, 3, 1]])
    moved = np.array([[1, 1, 2, 0], [1, 2, 0, 1]])
    images = np.zeros((2, 64, 64, 3), dtype=np.uint8)  # the oracle reads the macrostates
    with pytest.raises(ConfigError, match="episode_start=False continues an episode"):
        load_agent(tmp_path).act(images, states, episode_start=False)
    first = agent.act(images, states)
    second = agent.act(images, moved, episode_start=np.array([False, True]))
    mu0, _ = agent.encoder.encode(images, states)
    mu1, _ = agent.encoder.encode(images, moved)
    m = agent.model.members[0].explain(mu0[:1], torch.as_tensor(first[:1]), mu1[:1])
    belief = torch.cat([fuse(m, mu1[:1], 0.5), mu1[1:]])
    assert np.array_equal(second, agent.controller(belief).argmax(-1).numpy())
    # the test episodes' tracker is the same filter
    assert belief_tracker(agent, 7) is not None
    assert belief_tracker(load_agent(tmp_path), 7).weight == 0.5


def test_test_episodes_of_any_env_restart_the_beliefs_of_copies_that_reset():
    model = WorldModel(2, n_actions=3, dropout=0.0)
    tracker = BeliefTracker(model, 0.5, n=4, latent_dim=2)
    tracker.observe(torch.zeros(4, 2), torch.arange(4))
    policy = GreedyPolicy(None, None, tracker)
    policy.restart(np.array([1, 3]))
    assert tracker.started.tolist() == [True, False, True, False]


def test_the_component_that_explains_the_observation_is_ms_outcome_the_image_shows():
    # two outcomes: the hand kept (weight 0.8, at 0) or moved (weight 0.2, at 4)
    m = Mixture(torch.log(torch.tensor([[0.8, 0.2]])), torch.tensor([[[0.0, 0.0], [4.0, 4.0]]]),
                torch.full((1, 2, 2), 0.5))  # fmt: skip
    near_moved, between = torch.tensor([[3.5, 3.8]]), torch.tensor([[2.0, 2.0]])
    assert torch.equal(responsible_mean(m, near_moved), torch.tensor([[4.0, 4.0]]))
    assert torch.equal(responsible_mean(m, between), torch.tensor([[0.0, 0.0]]))  # the weight
    assert torch.equal(mixture_mode(m), torch.tensor([[0.0, 0.0]]))


class DeviceEncoder(OracleEncoder):
    """The oracle's means handed over on ``device``, as V on a GPU hands them."""

    def __init__(self, device: str) -> None:
        super().__init__()
        self.device = device

    def encode(self, images, states):
        mu, sigma = super().encode(images, states)
        return mu.to(self.device), sigma.to(self.device)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
@pytest.mark.parametrize("v_device, m_device", [("cuda", "cpu"), ("cpu", "cuda"), ("cuda", "cuda")])
def test_the_belief_lives_on_ms_device_whatever_vs(v_device, m_device):
    """V on a GPU and C and M on the CPU (a study's snapshot agents), or the other way round:
    the same actions and beliefs as all on the CPU."""
    torch.manual_seed(0)
    model = WorldModel(OracleEncoder().latent_dim, n_actions=6, dropout=0.0)
    controller = Controller(OracleEncoder().latent_dim, 6)
    rng = np.random.default_rng(0)
    states = [rng.integers(0, [4, 4, 4, 3], size=(5, 4)) for _ in range(3)]
    images = np.zeros((5, 64, 64, 3), dtype=np.uint8)

    def episode(encoder, model, controller):
        tracker = BeliefTracker(model, 0.5, n=5, latent_dim=model.members[0].latent_dim)
        actions = [greedy_actions(controller, encoder, images, s, tracker, np.arange(5))
                   for s in states]  # fmt: skip
        return np.stack(actions), tracker.belief.cpu()

    expected = episode(OracleEncoder(), model, controller)
    got = episode(DeviceEncoder(v_device), copy.deepcopy(model).to(m_device),
                  copy.deepcopy(controller).to(m_device))  # fmt: skip
    assert np.array_equal(got[0], expected[0])
    assert torch.allclose(got[1], expected[1], atol=1e-5)
