"""C: epsilon schedule, TD targets and updates (the population form, which training uses)."""

import math

import pytest
import torch

from imagine.models.controller import Controller, PopulationController, epsilon


def test_epsilon_schedule_of_the_paper():
    assert epsilon(0) == pytest.approx(0.8)
    assert epsilon(100) == pytest.approx(0.001 + 0.799 * math.exp(-3.0))
    assert epsilon(10_000) == pytest.approx(0.001)
    assert epsilon(10) > epsilon(11) > epsilon(12)


def test_architecture():
    c = Controller(latent_dim=8)
    sizes = [m.out_features for m in c.q if isinstance(m, torch.nn.Linear)]
    assert sizes == [512, 256, 128, 6]
    assert PopulationController([c]).target is None  # the paper: no target network


def batch(n=64, seed=0, agents=2):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(agents, n, 8, generator=g), torch.randint(6, (agents, n), generator=g),
            torch.randn(agents, n, generator=g) * 5, torch.randn(agents, n, 8, generator=g),
            (torch.rand(agents, n, generator=g) < 0.3).float())  # fmt: skip


def population(agents=2, **kwargs):
    torch.manual_seed(0)
    controllers = [Controller(8) for _ in range(agents)]
    return controllers, PopulationController(controllers, **kwargs)


def test_an_update_lowers_the_td_error_of_the_agents_that_update():
    _, c = population()
    z, a, r, nz, d = batch()

    def td_error():
        y = c.td_target(r, nz, d)
        with torch.no_grad():
            return ((c.q(z).gather(-1, a[..., None]).squeeze(-1) - y) ** 2).mean(-1)

    before = td_error()
    c.update(z, a, r, nz, d, agents=[0])
    after = td_error()
    assert after[0] < before[0] and after[1] == before[1]  # agent 1 sat out
    assert c.updates.tolist() == [1, 0]
    # Without bootstrapping (all terminal) repeated updates fit the rewards.
    done = torch.ones_like(d)
    losses = [c.update(z, a, r, nz, done, agents=[0, 1]) for _ in range(100)]
    assert (losses[-1] < 0.2 * losses[0]).all()


def test_terminal_targets_do_not_bootstrap():
    _, c = population(gamma=0.9)
    _, _, r, nz, d = batch()
    y = c.td_target(r, nz, torch.ones_like(d))
    assert torch.allclose(y, r)
    y = c.td_target(r, nz, torch.zeros_like(d))
    assert torch.allclose(y, r + 0.9 * c.q(nz).max(-1).values.detach())


def test_target_network_and_double_dqn_options():
    _, c = population(target_update_period=3, double_dqn=True)
    z, a, r, nz, d = batch()
    frozen = [p.clone() for p in c.target.parameters()]
    c.update(z, a, r, nz, d, agents=[0, 1])
    c.update(z, a, r, nz, d, agents=[0, 1])
    c.update(z, a, r, nz, d, agents=[0])  # agent 0's third update copies its Q into its target
    for t, q, f in zip(c.target.parameters(), c.q.parameters(), frozen, strict=True):
        assert torch.equal(t[0], q[0]) and torch.equal(t[1], f[1])
    best = c.q(nz).argmax(-1, keepdim=True)
    expected = r + 0.99 * (1 - d) * c.target(nz).gather(-1, best).squeeze(-1)
    assert torch.allclose(c.td_target(r, nz, d), expected)


def test_epsilon_greedy_actions():
    controllers, c = population()
    z = torch.randn(2, 2000, 8)
    g = torch.Generator().manual_seed(0)
    greedy = torch.stack([controllers[i](z[i]).argmax(-1) for i in range(2)])
    assert torch.equal(c.act(z, [0.0, 0.0], [g, g]), greedy)
    explored = c.act(z, [1.0, 0.0], [g, g])
    assert set(explored[0].tolist()) == set(range(6)) and torch.equal(explored[1], greedy[1])
    mixed = c.act(z, [0.5, 0.5], [g, None])  # agent 1 draws nothing: greedy
    agree = float((mixed[0] == greedy[0]).float().mean())
    assert 0.5 < agree < 0.66  # 1 - eps + eps / 6 = 0.583
    assert torch.equal(mixed[1], greedy[1])
