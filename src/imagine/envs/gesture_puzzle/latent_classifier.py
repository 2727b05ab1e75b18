"""Telling which macrostate a latent shows (docs/design.md section 3, model generalization).

A small probe reads V's latent: given the encoded means of labelled images, it learns each
cube's arrow direction and the pointed cube, one softmax head per factor over a shared hidden
layer. Later parts use it to judge what the world model M predicts: a predicted next latent is
right when the probe reads the true next macrostate from it.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from imagine.envs.gesture_puzzle.rules import N_CUBES, N_DIRECTIONS

FACTORS = ("cube0", "cube1", "cube2", "hand")
_CLASSES = (N_DIRECTIONS,) * N_CUBES + (N_CUBES,)


class LatentClassifier(nn.Module):
    """An MLP probe from a latent (N, latent_dim) to the macrostate (N, 4); with ``hidden=0``
    a linear probe (one softmax regression per factor), which reads only what V lays out
    linearly."""

    def __init__(self, latent_dim: int = 8, hidden: int = 128) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.register_buffer("mean", torch.zeros(latent_dim))
        self.register_buffer("scale", torch.ones(latent_dim))
        if hidden > 0:
            self.body: nn.Module = nn.Sequential(
                nn.Linear(latent_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
            )
        else:
            self.body = nn.Identity()
        self.heads = nn.Linear(hidden or latent_dim, sum(_CLASSES))

    def logits(self, z: torch.Tensor) -> list[torch.Tensor]:
        """Per-factor logits: three (N, 4) for the arrows, one (N, 3) for the hand."""
        out = self.heads(self.body((z - self.mean) / self.scale))
        return list(out.split(_CLASSES, dim=-1))

    @torch.no_grad()
    def predict(self, z: torch.Tensor) -> torch.Tensor:
        """The macrostate (d0, d1, d2, h) each latent shows, int64 (N, 4)."""
        return torch.stack([logit.argmax(-1) for logit in self.logits(z)], dim=-1)

    def fit(
        self,
        z: torch.Tensor,
        states: torch.Tensor,
        steps: int = 1500,
        lr: float = 3e-3,
        seed: int = 0,
    ) -> list[float]:
        """Fit on latents and their macrostates by full-batch Adam; returns the losses."""
        torch.manual_seed(seed)
        self.mean.copy_(z.mean(0))
        self.scale.copy_(z.std(0).clamp_min(1e-6))
        optimizer = torch.optim.Adam(self.parameters(), lr=lr)
        states = torch.as_tensor(states, dtype=torch.int64)
        losses = []
        for _ in range(steps):
            loss = sum(
                F.cross_entropy(logit, states[:, i]) for i, logit in enumerate(self.logits(z))
            )
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
        return losses

    def accuracy(self, z: torch.Tensor, states: torch.Tensor) -> dict[str, float]:
        """Fraction right for each factor and for the whole macrostate."""
        predicted = self.predict(z)
        states = torch.as_tensor(states, dtype=torch.int64)
        right = predicted == states
        result = {name: float(right[:, i].float().mean()) for i, name in enumerate(FACTORS)}
        result["macrostate"] = float(right.all(-1).float().mean())
        return result
