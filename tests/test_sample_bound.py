"""The bound on M's draws (`imagine vae report`, scripts/m_sample_bound.py): the mixture fit
recovers a known mixture, and the draws of a mixture follow its weights, so the "5 diagonal
components" row is what an M of that form fitted to each cloud would draw."""

from __future__ import annotations

import torch

from imagine.envs.gesture_puzzle.vision_report import diagonal_mixture, mixture_draws


def two_clouds(groups: int, n: int, generator: torch.Generator) -> torch.Tensor:
    """Per group, 30% of the points around (-3, 0) with scale 0.5 and 70% around (+3, 1) with
    scale 0.2 (G, n, 2)."""
    first = torch.rand(groups, n, 1, generator=generator) < 0.3
    centre = torch.where(first, torch.tensor([-3.0, 0.0]), torch.tensor([3.0, 1.0]))
    scale = torch.where(first, torch.tensor(0.5), torch.tensor(0.2))
    return centre + scale * torch.randn(groups, n, 2, generator=generator)


def test_diagonal_mixture_recovers_two_components():
    x = two_clouds(4, 2000, torch.Generator().manual_seed(0))
    weight, mean, var = diagonal_mixture(x, 2)
    order = mean[..., 0].argsort(-1)  # the component at -3 first
    weight = weight.gather(1, order)
    mean = mean.gather(1, order[..., None].expand(-1, -1, 2))
    var = var.gather(1, order[..., None].expand(-1, -1, 2))
    assert torch.allclose(weight, torch.tensor([0.3, 0.7]).expand(4, 2), atol=0.03)
    assert torch.allclose(mean, torch.tensor([[-3.0, 0.0], [3.0, 1.0]]).expand(4, 2, 2), atol=0.06)
    assert torch.allclose(var.sqrt(), torch.tensor([[0.5, 0.5], [0.2, 0.2]]).expand(4, 2, 2),
                          atol=0.04)  # fmt: skip


def test_mixture_draws_follow_the_weights_and_components():
    weight = torch.tensor([[0.25, 0.75]])
    mean = torch.tensor([[[-5.0], [5.0]]])
    var = torch.tensor([[[0.01], [0.04]]])
    draws = mixture_draws(weight, mean, var, 20000, torch.Generator().manual_seed(1))
    assert draws.shape == (1, 20000, 1)
    low = draws[..., 0] < 0
    assert abs(low.float().mean().item() - 0.25) < 0.015
    assert abs(draws[low].std().item() - 0.1) < 0.01
    assert abs(draws[~low].mean().item() - 5.0) < 0.01
