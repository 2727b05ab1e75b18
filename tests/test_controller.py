"""C: epsilon schedule, TD targets and updates."""

import math

import pytest
import torch

from imagine.controller import Controller, epsilon


def test_epsilon_schedule_of_the_paper():
    assert epsilon(0) == pytest.approx(0.8)
    assert epsilon(100) == pytest.approx(0.001 + 0.799 * math.exp(-3.0))
    assert epsilon(10_000) == pytest.approx(0.001)
    assert epsilon(10) > epsilon(11) > epsilon(12)


def test_architecture():
    c = Controller(latent_dim=8)
    sizes = [m.out_features for m in c.q if isinstance(m, torch.nn.Linear)]
    assert sizes == [512, 256, 128, 6]
    assert c.target is None  # the paper: no target network


def batch(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 8, generator=g), torch.randint(6, (n,), generator=g),
            torch.randn(n, generator=g) * 5, torch.randn(n, 8, generator=g),
            (torch.rand(n, generator=g) < 0.3).float())  # fmt: skip


def test_an_update_lowers_the_td_error():
    torch.manual_seed(0)
    c = Controller(8)
    z, a, r, nz, d = batch()
    y = c.td_target(r, nz, d)
    with torch.no_grad():
        before = float(((c(z).gather(1, a[:, None]).squeeze(1) - y) ** 2).mean())
    c.update(z, a, r, nz, d)
    with torch.no_grad():
        after = float(((c(z).gather(1, a[:, None]).squeeze(1) - y) ** 2).mean())
    assert after < before
    # Without bootstrapping (all terminal) repeated updates fit the rewards.
    done = torch.ones_like(d)
    losses = [c.update(z, a, r, nz, done) for _ in range(100)]
    assert losses[-1] < 0.2 * losses[0]


def test_terminal_targets_do_not_bootstrap():
    c = Controller(8, gamma=0.9)
    _, _, r, nz, d = batch()
    y = c.td_target(r, nz, torch.ones_like(d))
    assert torch.allclose(y, r)
    y = c.td_target(r, nz, torch.zeros_like(d))
    assert torch.allclose(y, r + 0.9 * c(nz).max(-1).values.detach())


def test_target_network_and_double_dqn_options():
    torch.manual_seed(0)
    c = Controller(8, target_update_period=3, double_dqn=True)
    z, a, r, nz, d = batch()
    frozen = [p.clone() for p in c.target.parameters()]
    c.update(z, a, r, nz, d)
    c.update(z, a, r, nz, d)
    assert all(torch.equal(p, q) for p, q in zip(c.target.parameters(), frozen, strict=True))
    c.update(z, a, r, nz, d)  # the third update copies Q into the target
    assert all(
        torch.equal(p, q) for p, q in zip(c.target.parameters(), c.q.parameters(), strict=True)
    )
    best = c.q(nz).argmax(-1, keepdim=True)
    expected = r + 0.99 * (1 - d) * c.target(nz).gather(-1, best).squeeze(-1)
    assert torch.allclose(c.td_target(r, nz, d), expected)


def test_epsilon_greedy_actions():
    c = Controller(8)
    z = torch.randn(2000, 8)
    g = torch.Generator().manual_seed(0)
    greedy = c(z).argmax(-1)
    assert torch.equal(c.act(z, 0.0, g), greedy)
    explored = c.act(z, 1.0, g)
    assert set(explored.tolist()) == set(range(6))
    mixed = c.act(z, 0.5, g)
    agree = float((mixed == greedy).float().mean())
    assert 0.5 < agree < 0.66  # 1 - eps + eps / 6 = 0.583
