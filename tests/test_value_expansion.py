"""Model-based value expansion (issue 16): C's H-step targets through M."""

import pytest
import torch

from imagine.config import AGENT_PRESETS, agent_preset
from imagine.errors import ConfigError
from imagine.learning.training import train
from imagine.learning.value_expansion import expanded_target, member_values, steve_target
from imagine.metrics import read_metrics
from imagine.models.controller import Controller, PopulationController
from imagine.models.world_model import PopulationWorldModel, WorldModel


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


def test_a_presets_value_expansion_is_the_augmented_agents(monkeypatch):
    """A preset with H > 0 for its augmented agent still has a baseline (which has no M): it
    goes without H, while H given explicitly to a baseline stays an error."""
    smoke = AGENT_PRESETS["smoke"]
    monkeypatch.setitem(
        AGENT_PRESETS, "smoke", {**smoke, "augmented": {**smoke["augmented"], "value_expansion": 2}}
    )
    assert agent_preset("smoke").value_expansion == 2
    assert agent_preset("smoke", method="baseline").value_expansion == 0
    assert agent_preset("smoke", method="augmented", value_expansion=1).value_expansion == 1
    with pytest.raises(ConfigError, match="value_expansion needs M"):
        agent_preset("smoke", method="baseline", value_expansion=2)


class ShiftEnsemble(ShiftModel):
    """An ensemble of K ShiftModels: member k moves z by 1 + k * ``part`` (all agree at 0);
    ``endless``: no state ends an episode."""

    def __init__(self, members: int, part: float, endless: bool = False) -> None:
        self.ensemble, self.part, self.endless = members, part, endless

    def is_terminal(self, z):
        if self.endless:
            return torch.zeros(z.shape[:-1], dtype=torch.bool)
        return super().is_terminal(z)

    def member_paths(self, z, action):
        k = torch.arange(self.ensemble, dtype=z.dtype).view(1, -1, 1, 1)
        return z + 1.0 + k * self.part


def steve_setting():
    torch.manual_seed(0)
    controller = PopulationController([Controller(2), Controller(2)], gamma=0.9)
    z = torch.tensor([[[0.5, 0.0], [1.0, 2.0]], [[-3.0, 1.0], [0.2, 0.1]]])  # (P=2, B=2, D)
    next_z = z + 1.0
    action = torch.tensor([[0, 3], [5, 1]])
    reward, done = torch.tensor([[-1.0, 50.0], [-5.0, -1.0]]), torch.tensor([[0.0, 1.0], [0, 0]])
    return controller, z, action, reward, next_z, done


def test_steve_with_agreeing_members_weighs_each_horizon_by_its_bootstrap_share():
    """Members that agree leave only the bootstrap's variance, (c_j)^2 sigma_Q^2: horizon j's
    weight is proportional to 1 / c_j^2 (a horizon past M's end, c_j = 0, takes it all)."""
    controller, z, action, reward, next_z, done = steve_setting()
    horizon = 2
    y, mean_horizon = steve_target(controller, ShiftEnsemble(3, 0.0), z, action, reward,
                                   next_z, done, horizon)  # fmt: skip
    q = controller.q(z).gather(-1, action.unsqueeze(-1)).squeeze(-1)
    q_variance = (controller.td_target(reward, next_z, done) - q).square().mean(-1, keepdim=True)
    candidates, weights = [], []
    for j in range(horizon + 1):  # W_j from expanded_target's j-step return, c_j by hand
        inner_j = expanded_target(controller, ShiftModel(), torch.zeros_like(reward), next_z,
                                  torch.zeros_like(done), j) / 0.9  # fmt: skip
        c_j = torch.ones_like(reward)
        for i in range(1, j + 1):
            c_j = c_j * 0.9 * (1 - ((next_z + i)[..., 0] > 2.5).float())
        candidates.append(inner_j)
        weights.append(1 / (c_j.square() * q_variance + 1e-8))
    w = torch.stack(weights) / torch.stack(weights).sum(0)
    expected = reward + 0.9 * (1 - done) * (w * torch.stack(candidates)).sum(0)
    assert torch.allclose(y, expected, atol=1e-4)
    per_row = (w * torch.tensor([0.0, 1, 2]).view(-1, 1, 1)).sum(0)
    going = 1 - done  # a real transition that ended does not count
    assert torch.allclose(mean_horizon, (per_row * going).sum(-1) / going.sum(-1))
    assert (mean_horizon > 1.0).all()  # agreeing members: the longer horizons weigh more


def test_steve_returns_to_equation_1_where_the_members_part():
    """The further apart the members' states (and so their Q'), the less the expanded
    horizons weigh: at the limit, y is equation 1's."""
    controller, z, action, reward, next_z, done = steve_setting()
    plain = controller.td_target(reward, next_z, done)
    gaps, horizons = [], []
    for part in (1e2, 1e4, 1e8):
        parting = ShiftEnsemble(3, part, endless=True)
        y, mean_horizon = steve_target(controller, parting, z, action, reward, next_z, done, 3)
        gaps.append((y - plain).abs().max())
        horizons.append(mean_horizon.max())
    assert gaps[2] < 0.01 < gaps[0]
    assert horizons[0] > horizons[1] > horizons[2] and horizons[2] < 1e-3


def test_each_member_rolls_out_on_its_own_rows():
    torch.manual_seed(1)
    models = [WorldModel(3, dropout=0.0, ensemble=3) for _ in range(2)]
    population = PopulationWorldModel(models)
    z, action = torch.randn(2, 3, 4, 3), torch.randint(0, 6, (2, 3, 4))
    paths = population.member_paths(z, action)
    for i, model in enumerate(models):
        for k, member in enumerate(model.members):
            assert torch.allclose(paths[i, k], member.most_likely(z[i, k], action[i, k]),
                                  atol=1e-5)  # fmt: skip


def two_ensemble_agents(seed: int):
    """Two agents' ensemble Ms of three members (dropout configured, not applied) and Cs."""
    torch.manual_seed(seed)
    models = [WorldModel(3, dropout=0.5, ensemble=3) for _ in range(2)]
    for m in models:
        m.eval()
    controller = PopulationController([Controller(3), Controller(3)], gamma=0.9)
    return models, PopulationWorldModel(models), controller


def test_member_values_are_each_members_own_rollout_through_m():
    """W_j^k of a real ensemble M (dropout configured, not applied) is member k's own j-step
    return, by hand through ``WorldModel.members[k]``; member 0's W_H is MVE's."""
    models, population, controller = two_ensemble_agents(seed=2)
    next_z = torch.randn(2, 4, 3)
    horizon = 2
    values, continuations = member_values(controller, population, next_z, horizon)
    assert values.shape == continuations.shape == (horizon + 1, 2, 3, 4)
    for i, model in enumerate(models):
        for k, member in enumerate(model.members):
            z, partial, discount = next_z[i], torch.zeros(4), torch.ones(4)
            for j in range(horizon + 1):
                bootstrap = controller.bootstrap_value(z.expand(2, 4, 3))[i]
                assert torch.allclose(values[j, i, k], partial + discount * bootstrap, atol=1e-5)
                assert torch.allclose(continuations[j, i, k], discount)
                if j == horizon:
                    break
                action = controller.q(z.expand(2, 4, 3))[i].argmax(-1)
                z = member.most_likely(z, action)
                zz = z.expand(2, 4, 3)
                partial = partial + discount * population.predict_reward(zz)[i]
                discount = discount * 0.9 * (1 - population.is_terminal(zz)[i].float())
    zero = torch.zeros(2, 4)
    mve = expanded_target(controller, population, zero, next_z, zero, horizon) / 0.9
    assert torch.allclose(values[horizon, :, 0], mve, atol=1e-5)


def test_mve_follows_the_first_member_or_the_members_mean_mode(tmp_path):
    """``value_expansion_members``: member 0's modes (the default) or the members' mean mode,
    by hand through ``WorldModel.members[0]`` and ``WorldModel.most_likely``; an agent
    trains with the mean, and a bad value is refused."""
    models, population, controller = two_ensemble_agents(seed=3)
    next_z, zero, horizon = torch.randn(2, 4, 3), torch.zeros(2, 4), 2

    def by_hand(step) -> torch.Tensor:
        z, partial, discount = next_z, torch.zeros(2, 4), torch.ones(2, 4)
        for _ in range(horizon):
            action = controller.q(z).argmax(-1)
            z = torch.stack([step(model, z[i], action[i]) for i, model in enumerate(models)])
            partial = partial + discount * population.predict_reward(z)
            discount = discount * 0.9 * (1 - population.is_terminal(z).float())
        return partial + discount * controller.bootstrap_value(z)

    first = expanded_target(controller, population, zero, next_z, zero, horizon) / 0.9
    mean = expanded_target(controller, population, zero, next_z, zero, horizon, "mean") / 0.9
    assert torch.allclose(first, by_hand(lambda m, z, a: m.members[0].most_likely(z, a)),
                          atol=1e-5)  # fmt: skip
    assert torch.allclose(mean, by_hand(lambda m, z, a: m.most_likely(z, a)), atol=1e-5)
    assert not torch.allclose(first, mean)  # three members that differ
    config = agent_preset("smoke", encoder="oracle", episodes=30, imagination_start=10,
                          value_expansion=2, model_ensemble=2, imagination_gate="mask",
                          value_expansion_members="mean")  # fmt: skip
    agent = train(config, tmp_path, threads=1)
    assert agent.episode == 30 and agent.config.value_expansion_members == "mean"
    rows = read_metrics(tmp_path / "metrics.csv")
    losses = [r["losses/controller_real"] for r in rows if "losses/controller_real" in r]
    assert losses and all(torch.isfinite(torch.tensor(losses)))
    with pytest.raises(ConfigError, match="value_expansion_members must be one of"):
        agent_preset("fast", value_expansion_members="median")


def test_an_agent_learns_with_steve_targets(tmp_path):
    config = agent_preset("smoke", encoder="oracle", episodes=40, imagination_start=10,
                          value_expansion=2, value_expansion_weighting="steve",
                          model_ensemble=2)  # fmt: skip
    agent = train(config, tmp_path, threads=1)
    assert agent.episode == 40
    rows = read_metrics(tmp_path / "metrics.csv")
    horizons = [r["charts/expansion_horizon"] for r in rows if "charts/expansion_horizon" in r]
    assert horizons and all(0.0 <= h <= 2.0 for h in horizons)
    assert all(torch.isfinite(torch.tensor(r["losses/controller_real"])) for r in rows
               if "losses/controller_real" in r)  # fmt: skip


def test_steve_needs_an_ensemble_and_a_horizon():
    with pytest.raises(ConfigError, match="must be one of"):
        agent_preset("fast", value_expansion_weighting="stevee")
    with pytest.raises(ConfigError, match="model_ensemble >= 2"):
        agent_preset("fast", value_expansion=2, value_expansion_weighting="steve",
                     model_ensemble=1)  # fmt: skip
    with pytest.raises(ConfigError, match="value_expansion >= 1"):
        agent_preset("fast", model_ensemble=3, value_expansion=0, value_expansion_weighting="steve")


def test_a_studys_value_expansion_and_belief_are_its_augmented_agents():
    """`imagine reproduce --set value_expansion=2` expands the augmented agents' targets; the
    study's baselines (no M) go without it, as they go without the preset's belief."""
    from imagine.study.experiments import Job, job_config
    from imagine.study.reproduce import StudyConfig

    overrides = {"value_expansion": 2, "belief": "filtered"}
    StudyConfig(preset="smoke", overrides=overrides)  # valid for both methods
    base, aug = (
        job_config(Job("unused", "hard", m, 0, (300,), preset="smoke", encoder="oracle",
                       overrides=tuple(overrides.items())), 300)
        for m in ("baseline", "augmented")
    )  # fmt: skip
    assert (base.value_expansion, base.belief) == (0, "observation")
    assert (aug.value_expansion, aug.belief) == (2, "filtered")
    fast = agent_preset("fast", method="baseline")  # the preset's own
    assert (fast.value_expansion, fast.belief) == (0, "observation")
    with pytest.raises(ConfigError, match="value_expansion must be 0 to 3"):
        StudyConfig(preset="smoke", overrides={"value_expansion": 4})
