"""M: the MDN's likelihood and sampling, the r- and d-networks, and M's update."""

import math

import pytest
import torch

from imagine.models.world_model import (
    MDN,
    Mixture,
    PopulationWorldModel,
    RewardNet,
    TerminalNet,
    WorldModel,
    log_cosh,
    mixture_nll,
)


def test_mixture_nll_against_a_hand_computed_value():
    mixture = Mixture(
        log_pi=torch.log(torch.tensor([[0.25, 0.75]])),
        mu=torch.tensor([[[0.0], [1.0]]]),
        sigma=torch.tensor([[[1.0], [2.0]]]),
    )
    x = 0.5
    p = 0.25 * math.exp(-0.5 * x**2) / math.sqrt(2 * math.pi) + 0.75 * math.exp(
        -0.5 * ((x - 1) / 2) ** 2
    ) / (2 * math.sqrt(2 * math.pi))
    assert float(mixture_nll(mixture, torch.tensor([[x]]))) == pytest.approx(-math.log(p), rel=1e-6)


def test_mixture_nll_is_finite_far_from_every_component():
    mixture = Mixture(torch.log(torch.tensor([[0.5, 0.5]])), torch.zeros(1, 2, 3),
                      torch.full((1, 2, 3), 1e-3))  # fmt: skip
    value = mixture_nll(mixture, torch.full((1, 3), 100.0))
    assert torch.isfinite(value).all() and float(value) > 1e9


def test_mdn_architecture_and_shapes():
    mdn = MDN(latent_dim=8)
    hidden = [m for m in mdn.body if isinstance(m, torch.nn.Linear)]
    assert [m.out_features for m in hidden] == [256, 256, 256]
    assert sum(isinstance(m, torch.nn.Dropout) for m in mdn.body) == 3
    m = mdn(torch.randn(4, 8), torch.tensor([0, 1, 5, 2]))
    assert m.log_pi.shape == (4, 5) and m.mu.shape == (4, 5, 8) and (m.sigma > 0).all()
    assert torch.allclose(m.log_pi.exp().sum(-1), torch.ones(4))


def test_mdn_learns_a_two_mode_next_state_distribution():
    """From one state and action the next state is +1 or -1 with equal odds: both modes are
    sampled afterwards, and the most likely state is one of them, not their mean."""
    torch.manual_seed(0)
    mdn = MDN(latent_dim=1, n_actions=2)
    optimizer = torch.optim.Adam(mdn.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(0)
    z, a = torch.zeros(256, 1), torch.zeros(256, dtype=torch.int64)
    for _ in range(600):
        sign = torch.randint(2, (256, 1), generator=g) * 2.0 - 1.0
        target = sign + 0.05 * torch.randn(256, 1, generator=g)
        loss = mdn.loss(z, a, target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    mdn.eval()
    samples = mdn.sample(torch.zeros(2000, 1), torch.zeros(2000, dtype=torch.int64), g)
    near_plus = float(((samples - 1).abs() < 0.3).float().mean())
    near_minus = float(((samples + 1).abs() < 0.3).float().mean())
    assert near_plus > 0.3 and near_minus > 0.3 and near_plus + near_minus > 0.9
    best = mdn.most_likely(torch.zeros(1, 1), torch.zeros(1, dtype=torch.int64))
    assert abs(abs(float(best)) - 1) < 0.2


def rule(z):
    """A known rule: states with z0 > 1 are goals (+50), z0 < -1 illegal (-5), else -1."""
    reward = torch.where(z[:, 0] > 1, 50.0, torch.where(z[:, 0] < -1, -5.0, -1.0))
    return reward, (z[:, 0].abs() > 1).float()


def test_r_and_d_networks_learn_a_known_rule():
    torch.manual_seed(0)
    r_net, d_net = RewardNet(2), TerminalNet(2)
    opt_r = torch.optim.Adam(r_net.parameters(), lr=1e-3)
    opt_d = torch.optim.Adam(d_net.parameters(), lr=1e-3)
    for _ in range(400):
        z = torch.randn(256, 2) * 1.5
        reward, done = rule(z)
        for opt, loss in ((opt_r, r_net.loss(z, reward)), (opt_d, d_net.loss(z, done))):
            opt.zero_grad()
            loss.backward()
            opt.step()
    r_net.eval()
    d_net.eval()
    z = torch.randn(2000, 2) * 1.5
    z = z[(z[:, 0].abs() - 1).abs() > 0.15]  # away from the boundaries
    reward, done = rule(z)
    assert float((d_net.is_terminal(z).float() == done).float().mean()) > 0.97
    with torch.no_grad():
        assert float(((r_net(z) - reward).abs() < 3).float().mean()) > 0.95


def test_log_cosh_is_stable():
    x = torch.tensor([0.0, 1.0, -3.0, 1000.0])
    expected = torch.log(torch.cosh(x[:3].double())).float()
    assert torch.allclose(log_cosh(x[:3]), expected, atol=1e-6)
    assert float(log_cosh(x[3:])) == pytest.approx(1000 - math.log(2))


def test_world_model_update_resamples_latents_and_lowers_losses():
    torch.manual_seed(0)
    models = [WorldModel(latent_dim=4), WorldModel(latent_dim=4)]
    population = PopulationWorldModel(models)
    gens = [torch.Generator().manual_seed(0), torch.Generator().manual_seed(1)]
    n = 512
    mu = torch.randn(n, 4)
    action = torch.randint(6, (n,))
    next_mu = mu.roll(1, dims=1) + (action[:, None] == 0).float()  # a known transition
    reward, done = rule(next_mu)
    single = {"mu": mu, "sigma": torch.full((n, 4), 0.01), "action": action,
              "next_mu": next_mu, "next_sigma": torch.full((n, 4), 0.01), "reward": reward,
              "done": done}  # fmt: skip
    batch = {k: torch.stack([v, v]) for k, v in single.items()}
    first = population.update(batch, gens)
    frozen = [p[1].clone() for p in population.parameters()]
    for _ in range(150):
        last = population.update(batch, [gens[0], None])  # agent 1 sits out
    assert set(first) == {"mdn", "reward", "terminal"}
    assert all(last[k][0] < first[k][0] for k in first)
    assert all(torch.equal(p[1], q) for p, q in zip(population.parameters(), frozen, strict=True))


def test_updates_of_r_and_d_alone_leave_the_mdn_as_it_is_and_lower_their_losses():
    """reward_updates: r and d learn on their own; the MDN's weights and Adam state stay."""
    torch.manual_seed(0)
    population = PopulationWorldModel([WorldModel(latent_dim=4, dropout=0.0)])
    gens = [torch.Generator().manual_seed(0)]
    n = 256
    next_mu = torch.randn(1, n, 4)
    reward, done = rule(next_mu[0])
    batch = {"mu": torch.randn(1, n, 4), "sigma": torch.full((1, n, 4), 0.01),
             "action": torch.randint(6, (1, n)), "next_mu": next_mu,
             "next_sigma": torch.full((1, n, 4), 0.01), "reward": reward[None],
             "done": done[None]}  # fmt: skip
    population.update(batch, gens)  # one joint update: every network has Adam state
    mdn = [p.clone() for p in population.mdn.parameters()]
    first = population.update(batch, gens, mdn=False)
    for _ in range(100):
        last = population.update(batch, gens, mdn=False)
    assert set(first) == {"reward", "terminal"}
    assert all(last[k][0] < 0.5 * first[k][0] for k in first)
    assert all(torch.equal(p, q) for p, q in zip(population.mdn.parameters(), mdn, strict=True))


def test_population_samples_come_from_each_agents_mixture():
    torch.manual_seed(0)
    models = [WorldModel(latent_dim=2, dropout=0.0) for _ in range(2)]
    population = PopulationWorldModel(models)
    z, a = torch.randn(2, 3, 2), torch.randint(6, (2, 3))
    g = torch.Generator().manual_seed(3)
    drawn = population.sample(z, a, [None, g])
    assert torch.equal(drawn[0], torch.zeros(3, 2))  # no generator, no draw
    expected = models[1].mdn.sample(z[1], a[1], torch.Generator().manual_seed(3))
    assert torch.allclose(drawn[1], expected, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_squared_error_teaches_r_a_rare_large_reward_that_log_cosh_does_not(seed):
    """reward_loss: with 2% of next states worth +50 and the rest -1, 100 updates of r with
    the squared error predict most of the +50; with log-cosh (gradient at most 1 per
    transition) r barely leaves the common -1."""

    def goal_prediction(loss: str) -> tuple[float, float]:
        torch.manual_seed(seed)
        model = WorldModel(latent_dim=4, dropout=0.0, reward_hidden=64)
        population = PopulationWorldModel([model], reward_loss=loss)
        gens = [torch.Generator().manual_seed(0)]
        next_mu = torch.randn(1, 256, 4, generator=torch.Generator().manual_seed(1))
        goal = next_mu[0, :, 0] > 2.0
        batch = {"mu": torch.randn(1, 256, 4), "sigma": torch.full((1, 256, 4), 0.01),
                 "action": torch.randint(6, (1, 256)), "next_mu": next_mu,
                 "next_sigma": torch.full((1, 256, 4), 0.01),
                 "reward": torch.where(goal, 50.0, -1.0)[None],
                 "done": goal.float()[None]}  # fmt: skip
        for _ in range(100):
            population.update(batch, gens, mdn=False)
        r = population.predict_reward(next_mu)[0]
        assert goal.sum() >= 3
        return float(r[goal].mean()), float(r[~goal].mean())

    squared_goal, squared_rest = goal_prediction("mse")
    cosh_goal, cosh_rest = goal_prediction("logcosh")
    assert squared_goal > 25.0 and cosh_goal < 10.0
    assert abs(squared_rest + 1.0) < 0.5 and abs(cosh_rest + 1.0) < 0.5


def test_r_and_d_take_their_own_dropout_and_the_mdn_keeps_its_own():
    """reward_dropout: r and d without dropout beside an MDN with 20%; None keeps one rate."""
    assert WorldModel(4, dropout=0.2).reward_dropout == 0.2  # the paper's one rate
    population = PopulationWorldModel([WorldModel(4, dropout=0.2, reward_dropout=0.0)])
    assert (population.mdn.body.dropout, population.reward.dropout) == (0.2, 0.0)
    assert population.terminal.dropout == 0.0
    z, gens = torch.randn(1, 64, 4), [torch.Generator().manual_seed(0)]
    r = [population.reward(z, gens) for _ in range(2)]
    assert torch.equal(r[0], r[1])  # no masks drawn in training mode
    masked = PopulationWorldModel([WorldModel(4, dropout=0.2)])
    assert not torch.equal(masked.reward(z, gens), masked.reward(z, gens))
