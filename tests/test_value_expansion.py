"""Model-based value expansion (issue 16): C's H-step targets through M."""

import pytest
import torch

from imagine.config import agent_preset
from imagine.errors import ConfigError
from imagine.learning.training import train
from imagine.learning.value_expansion import expanded_target
from imagine.metrics import read_metrics
from imagine.models.controller import Controller, PopulationController


class ShiftModel:
    """A known M: every action moves z by +1 in each dimension, r = 2 everywhere, the end
    where the first dimension passes 2.5."""

    def mode(self, z, action):
        return z + 1.0

    def predict_reward(self, z):
        return torch.full(z.shape[:-1], 2.0)

    def is_terminal(self, z):
        return z[..., 0] > 2.5


def test_the_expanded_target_is_the_h_step_return_through_m():
    torch.manual_seed(0)
    controller = PopulationController([Controller(2), Controller(2)], gamma=0.9)
    z = torch.tensor([[[0.0, 0.0], [1.0, 5.0]], [[-3.0, 1.0], [0.2, 0.1]]])  # (P=2, B=2, D)
    reward, done = torch.tensor([[-1.0, 50.0], [-5.0, -1.0]]), torch.tensor([[0.0, 1.0], [0, 0]])
    value = lambda x: controller.q(x).max(-1).values  # noqa: E731  (no target network)
    for horizon in (0, 1, 2, 3):
        y = expanded_target(controller, ShiftModel(), reward, z, done, horizon)
        expected = value(z + horizon)
        for h in range(horizon, 0, -1):  # the state entered at step h is z + h
            ended = ((z + h)[..., 0] > 2.5).float()
            expected = 2.0 + 0.9 * (1 - ended) * expected
        expected = reward + 0.9 * (1 - done) * expected
        assert torch.allclose(y, expected, atol=1e-5), horizon
    plain = controller.td_target(reward, z, done)
    assert torch.equal(expanded_target(controller, ShiftModel(), reward, z, done, 0), plain)


def test_an_agent_learns_with_expanded_targets(tmp_path):
    config = agent_preset("smoke", encoder="oracle", episodes=40, imagination_start=10,
                          value_expansion=2)  # fmt: skip
    agent = train(config, tmp_path, threads=1)
    assert agent.episode == 40
    rows = read_metrics(tmp_path / "metrics.csv")
    assert all(torch.isfinite(torch.tensor(r["losses/controller_real"])) for r in rows
               if "losses/controller_real" in r)  # fmt: skip


def test_value_expansion_needs_m_and_a_short_horizon():
    with pytest.raises(ConfigError, match="value_expansion needs M"):
        agent_preset("fast", method="baseline", value_expansion=1)
    with pytest.raises(ConfigError, match="value_expansion must be 0 to 3"):
        agent_preset("fast", value_expansion=5)
