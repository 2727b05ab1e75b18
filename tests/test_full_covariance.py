"""M's mixture with full-covariance components (``model_covariance: full``): N(mu_k, L_k L_k^T)
with a learned Cholesky factor, for latents whose dimensions move together."""

import dataclasses

import pytest
import torch
from torch import distributions

from imagine.errors import ConfigError
from imagine.models.world_model import (
    MDN,
    Mixture,
    PopulationWorldModel,
    WorldModel,
    mixture_from_heads,
    mixture_nll,
    responsible_mean,
    sample_mixture,
    scale_tril,
    tril_size,
)


def random_mixture(n: int = 6, k: int = 3, d: int = 4, seed: int = 0) -> Mixture:
    g = torch.Generator().manual_seed(seed)
    heads = [torch.randn(n, size, generator=g) for size in (k, k * d, k * d, k * tril_size(d))]
    return mixture_from_heads(*heads[:3], d, 1e-3, tril=heads[3])


def test_the_factor_is_lower_triangular_with_the_scales_on_its_diagonal():
    m = random_mixture()
    factor = scale_tril(m)
    assert torch.equal(factor, factor.tril())
    assert torch.equal(factor.diagonal(dim1=-2, dim2=-1), m.sigma)
    assert (m.tril.diagonal(dim1=-2, dim2=-1) == 0).all() and (m.tril != 0).any()


def test_the_likelihood_is_torch_distributions_mixture_of_multivariate_normals():
    m = random_mixture()
    reference = distributions.MixtureSameFamily(
        distributions.Categorical(logits=m.log_pi),
        distributions.MultivariateNormal(m.mu, scale_tril=scale_tril(m)),
    )
    x = torch.randn(6, 4, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(mixture_nll(m, x), -reference.log_prob(x), rtol=1e-5, atol=1e-4)


def test_a_zero_factor_below_the_diagonal_is_the_diagonal_mixture_exactly():
    full = random_mixture()
    full = full._replace(tril=torch.zeros_like(full.tril))
    diagonal = full._replace(tril=None)
    x = torch.randn(6, 4, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(mixture_nll(full, x), mixture_nll(diagonal, x), atol=1e-5)
    assert torch.equal(responsible_mean(full, x), responsible_mean(diagonal, x))
    draws = [sample_mixture(m, torch.Generator().manual_seed(2)) for m in (full, diagonal)]
    assert torch.allclose(*draws, atol=1e-6)
    # and a new full-covariance MDN starts as a diagonal one: its factor's head is zero
    m = MDN(4, covariance="full")(torch.randn(5, 4), torch.tensor([0, 1, 2, 3, 4]))
    assert (m.tril == 0).all()


def test_draws_have_the_components_covariance_and_a_tempered_draw_tau_times_it():
    one = random_mixture(n=1, k=1, d=3)
    n = 100_000
    m = Mixture(*(t.expand(n, *t.shape[1:]) for t in one))
    covariance = scale_tril(one)[0, 0] @ scale_tril(one)[0, 0].T
    draws = sample_mixture(m, torch.Generator().manual_seed(0))
    assert torch.allclose(torch.cov(draws.T), covariance, atol=0.05 * covariance.abs().max())
    cold = sample_mixture(m, torch.Generator().manual_seed(0), temperature=0.25)
    assert torch.allclose(torch.cov(cold.T), 0.25 * covariance, atol=0.05 * covariance.abs().max())


def correlated_clouds(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Two classes in 2-D: each a cloud stretched along (1, 1) (std 1) and thin across it (std
    0.05), the classes 0.4 apart across it. The next state of action a is a draw of class a."""
    label = torch.randint(2, (n,), generator=g)
    along = torch.randn(n, generator=g)
    across = 0.05 * torch.randn(n, generator=g) + 0.2 * (2 * label - 1)
    points = torch.stack([along + across, along - across], -1) / 2**0.5
    return points, label


def classify(points: torch.Tensor) -> torch.Tensor:
    return ((points[:, 0] - points[:, 1]) > 0).long()


@pytest.mark.parametrize("covariance", ["diagonal", "full"])
def test_only_a_full_covariance_m_draws_next_states_inside_a_correlated_cloud(covariance):
    """V's clouds of one macrostate are correlated across dimensions; a diagonal Gaussian
    covers them with a box that spills into the neighbour, a full covariance does not."""
    torch.manual_seed(0)
    mdn = MDN(2, n_actions=2, n_components=1, hidden=32, layers=1, dropout=0.0,
              covariance=covariance)  # fmt: skip
    optimizer = torch.optim.Adam(mdn.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(600):
        target, action = correlated_clouds(256, g)
        loss = mdn.loss(torch.zeros(256, 2), action, target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    mdn.eval()
    action = torch.arange(2).repeat(2000)
    draws = mdn.sample(torch.zeros(4000, 2), action, g)
    right = float((classify(draws) == action).float().mean())
    if covariance == "full":
        assert right > 0.97
    else:
        assert right < 0.85  # the box: a perfect diagonal Gaussian is right on about 0.66


def test_population_m_with_full_covariance_learns_each_agents_own_and_exports_it():
    """Two agents' full-covariance M in one stack: each agent's mixture is its own MDN's, an
    update lowers the loss, and export/import carry the factor's head."""
    torch.manual_seed(0)
    models = [WorldModel(3, dropout=0.0, covariance="full", ensemble=2) for _ in range(2)]
    population = PopulationWorldModel(models)
    z, a = torch.randn(2, 5, 3), torch.randint(6, (2, 5))
    g = [torch.Generator().manual_seed(0), torch.Generator().manual_seed(1)]
    n = 64
    mu = torch.randn(2, 2 * n, 3, generator=g[0])
    action = torch.randint(6, (2, 2 * n), generator=g[0])
    along = torch.randn(2, 2 * n, 1, generator=g[0])
    next_mu = mu + (action[..., None] == 0).float() + along * torch.tensor([1.0, 1.0, 0.0])
    batch = {"mu": mu, "sigma": torch.full_like(mu, 0.1), "action": action, "next_mu": next_mu,
             "next_sigma": torch.full_like(mu, 0.1), "reward": -next_mu[..., 0],
             "done": (next_mu[..., 0] > 1).float()}  # fmt: skip
    first = population.update(batch, g, resample=False)["mdn"]
    for _ in range(100):
        last = population.update(batch, g, resample=False)["mdn"]
    assert (last < first - 1.0).all(), (first, last)
    zs, actions = population._each_member(z), population._each_member(a)
    with torch.no_grad():
        heads = population._heads(zs, actions)
    for i in range(2):
        exported = population.export_agent(i, WorldModel(3, covariance="full", ensemble=2))
        assert (exported.mdn.tril_head.weight != 0).any()
        for k, mdn in enumerate(exported.members):
            alone = mdn.eval()(z[i], a[i])
            together = population._mixture([h[i * 2 + k] for h in heads], z[i])
            assert torch.allclose(scale_tril(alone), scale_tril(together), atol=1e-6)
    population.import_agent(1, population.export_agent(0, WorldModel(3, covariance="full",
                                                                     ensemble=2)))  # fmt: skip
    with torch.no_grad():
        copied = population._heads(zs[[0, 1, 0, 1]], actions[[0, 1, 0, 1]])
    # agent 1 now has agent 0's factors
    assert torch.allclose(copied[3][0:2], copied[3][2:4], atol=1e-6)


def test_a_full_covariance_agent_trains_saves_and_loads(smoke_agent):
    config, agent = smoke_agent(model_covariance="full")
    assert agent.config.model_covariance == "full"
    assert (agent.model.mdn.tril_head.weight != 0).any()  # it learned off-diagonal factors
    with pytest.raises(ConfigError, match="model_covariance"):
        dataclasses.replace(config, model_covariance="spherical")
