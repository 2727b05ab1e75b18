"""scripts/m_snap.py: resampling a mixture onto a bank of real points keeps the mixture's
preference among them and draws only bank points."""

from __future__ import annotations

import torch

from imagine.models.world_model import Mixture, mixture_nll


def mixture(means: list[list[float]], sigma: float, weights: list[float]) -> Mixture:
    """One row: a diagonal mixture of the given means, one scale, the given weights."""
    mu = torch.tensor([means])
    return Mixture(torch.tensor([weights]).log(), mu, torch.full_like(mu, sigma))


def test_bank_density_is_the_mixture_density_at_each_bank_point(load_script):
    snap = load_script("m_snap")
    m = mixture([[0.0, 0.0], [1.0, 1.0]], 0.5, [0.3, 0.7])
    bank = torch.randn(2500, 2)
    got = snap.bank_log_density(m, bank, chunk=1000)  # several chunks
    assert got.shape == (1, 2500)
    one = Mixture(
        m.log_pi.expand(2500, -1), m.mu.expand(2500, -1, -1), m.sigma.expand(2500, -1, -1)
    )
    torch.testing.assert_close(got[0], -mixture_nll(one, bank))


def test_resampling_follows_the_mixture_among_bank_points(load_script):
    snap = load_script("m_snap")
    # two clusters of bank points; the mixture puts 80% of its weight on the first
    bank = torch.cat([torch.zeros(50, 2), torch.full((50, 2), 5.0)]) + 0.01 * torch.randn(100, 2)
    m = mixture([[0.0, 0.0], [5.0, 5.0]], 0.5, [0.8, 0.2])
    m = Mixture(*(x.expand(2, *x.shape[1:]) for x in m[:3]))  # two rows
    points, effective = snap.resample(m, bank, torch.Generator().manual_seed(0), draws=2000)
    assert points.shape == (2000, 2, 2)
    assert all((bank == p).all(-1).any() for p in points[:100, 0])  # only bank points
    first = (points.norm(dim=-1) < 1).float().mean(0)
    assert ((first - 0.8).abs() < 0.03).all()
    assert ((effective > 60) & (effective < 100)).all()  # spread over most of the bank


def test_a_narrow_mixture_resamples_the_nearest_bank_point(load_script):
    snap = load_script("m_snap")
    bank = torch.tensor([[0.0, 0.0], [0.3, 0.0], [3.0, 3.0]])
    m = mixture([[0.32, 0.01]], 0.01, [1.0])
    points, effective = snap.resample(m, bank, torch.Generator().manual_seed(0))
    torch.testing.assert_close(points, bank[1:2][None])
    assert effective.item() < 1.01
