"""M's cloud head (``model_cloud_head``): the mixture around M's predicted next point is a
function of that point alone, shared by every (state, action) that leads there."""

import dataclasses

import pytest
import torch

from imagine.errors import ConfigError
from imagine.models.world_model import MDN, PopulationWorldModel, WorldModel

CENTERS = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])


def two_blob_cloud(state: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Images of macrostate s in a 2-D V: two tight blobs 0.6 apart around its center (the
    spread a single Gaussian cannot draw from without landing between them)."""
    side = 2.0 * torch.randint(2, state.shape, generator=g) - 1.0
    offset = torch.stack([0.3 * side, torch.zeros_like(side)], -1)
    return CENTERS[state] + offset + 0.03 * torch.randn(*state.shape, 2, generator=g)


def test_a_cloud_head_m_learns_a_known_transition_and_draws_inside_the_next_cloud():
    """Action a takes macrostate s to (s + a) mod 3; every state's images are a two-blob cloud.
    The cloud-head MDN's draws land in the right macrostate and on its blobs, not between."""
    torch.manual_seed(0)
    mdn = MDN(2, n_actions=3, n_components=4, hidden=64, layers=2, dropout=0.0, residual=True,
              cloud_hidden=32)  # fmt: skip
    optimizer = torch.optim.Adam(mdn.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(1500):
        state, action = torch.randint(3, (256,), generator=g), torch.randint(3, (256,), generator=g)
        loss = mdn.loss(two_blob_cloud(state, g), action, two_blob_cloud((state + action) % 3, g))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert sum(losses[-100:]) / 100 < sum(losses[:100]) / 100 - 2.0
    mdn.eval()
    state, action = torch.randint(3, (3000,), generator=g), torch.randint(3, (3000,), generator=g)
    draws = mdn.sample(two_blob_cloud(state, g), action, g)
    nearest = torch.cdist(draws, CENTERS).argmin(-1)
    assert (nearest == (state + action) % 3).float().mean() > 0.98
    off_center = (draws - CENTERS[nearest])[:, 0].abs()
    # on a blob, not between the two (one Gaussian over both blobs: about 0.62)
    assert (off_center > 0.15).float().mean() > 0.8


def test_the_mixture_depends_on_the_input_only_through_the_predicted_point():
    """With the point head's weights zeroed every action predicts the same point z + b, so
    every action gets the same mixture; a plain MDN's still differ by action."""
    torch.manual_seed(0)
    mdn = MDN(3, n_actions=4, hidden=16, layers=1, dropout=0.0, residual=True, cloud_hidden=8)
    plain = MDN(3, n_actions=4, hidden=16, layers=1, dropout=0.0, residual=True)
    with torch.no_grad():
        mdn.point_head.weight.zero_()
    z, action = torch.randn(1, 3).expand(4, 3), torch.arange(4)
    with torch.no_grad():
        m, p = mdn(z, action), plain(z, action)
        expected = (z + mdn.point_head.bias).unsqueeze(1) + mdn.mu_head(
            mdn.cloud(z + mdn.point_head.bias)
        ).view(4, 5, 3)
    for t in (m.log_pi, m.mu, m.sigma):
        assert torch.allclose(t, t[:1].expand_as(t))
    assert torch.allclose(m.mu, expected, atol=1e-6)  # means: c + o_k(c)
    assert not torch.allclose(p.mu, p.mu[:1].expand_as(p.mu))


def test_a_population_m_with_cloud_heads_is_each_agents_own_and_exports_it():
    torch.manual_seed(0)
    models = [WorldModel(4, dropout=0.2, residual=True, ensemble=2, cloud_hidden=8)
              for _ in range(2)]  # fmt: skip
    population = PopulationWorldModel(models)
    z, a = torch.randn(2, 6, 4), torch.randint(6, (2, 6))
    with torch.no_grad():
        modes = population.eval().member_modes(z, a)
    for i, model in enumerate(models):
        for k, mdn in enumerate(model.eval().members):
            assert torch.allclose(modes[i, k], mdn.most_likely(z[i], a[i]), atol=1e-5)
    g = [torch.Generator().manual_seed(i) for i in range(2)]
    mu = torch.randn(2, 128, 4, generator=g[0])
    action = torch.randint(6, (2, 128), generator=g[0])
    next_mu = mu + 0.5 * (action[..., None] == 0).float()
    batch = {"mu": mu, "sigma": torch.full_like(mu, 0.05), "action": action, "next_mu": next_mu,
             "next_sigma": torch.full_like(mu, 0.05), "reward": -next_mu[..., 0],
             "done": torch.zeros(2, 128)}  # fmt: skip
    population.train()
    first = population.update(batch, g, resample=False)["mdn"]
    for _ in range(60):
        last = population.update(batch, g, resample=False)["mdn"]
    assert (last < first - 0.5).all(), (first, last)
    population.eval()
    with torch.no_grad():
        modes = population.member_modes(z, a)
    fresh = WorldModel(4, dropout=0.2, residual=True, ensemble=2, cloud_hidden=8)
    exported = population.export_agent(1, fresh).eval()
    assert torch.allclose(exported.members[1].most_likely(z[1], a[1]), modes[1, 1], atol=1e-5)
    population.import_agent(0, exported)
    with torch.no_grad():
        assert torch.allclose(population.member_modes(z[[1, 1]], a[[1, 1]])[0], modes[1],
                              atol=1e-5)  # fmt: skip


def test_a_cloud_head_agent_trains_saves_and_loads(smoke_agent):
    config, agent = smoke_agent(model_cloud_head=16, model_residual=True)
    assert agent.model.mdn.cloud[0].in_features == agent.encoder.latent_dim
    assert agent.model.mdn.pi_head.in_features == 16
    with pytest.raises(ConfigError, match="model_cloud_head needs"):
        dataclasses.replace(config, model_covariance="full")
    with pytest.raises(ConfigError, match="model_cloud_head must be >= 0"):
        dataclasses.replace(config, model_cloud_head=-1)
    with pytest.raises(ValueError, match="cloud head"):
        MDN(4, residual=False, cloud_hidden=8)
