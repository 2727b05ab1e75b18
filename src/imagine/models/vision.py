"""V: the beta-VAE that turns a scene into a latent state (paper sections III-B and V-B).

The architecture is the World Models convolutional VAE (Ha & Schmidhuber 2018) with an
8-dimensional latent: four 4x4 stride-2 convolutions (32, 64, 128, 256 channels) to 1024
features, linear maps to mu and log sigma, a linear map back to 1024 features and four
transposed convolutions (kernels 5, 5, 6, 6; channels 128, 64, 32, 3) to a 3 x 64 x 64 image.

The loss is the paper's equation (4) with the KL term weighted by beta (Higgins et al. 2017):
pixel-wise binary cross-entropy, summed over the image, plus beta times
KL(N(mu, sigma^2) || N(0, I)) = -1/2 sum_j (1 + log sigma_j^2 - mu_j^2 - sigma_j^2),
both per image and averaged over the batch. Sampling uses the reparameterization
z = mu + sigma * eps, eps ~ N(0, I).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

ACTIVE_VARIANCE = 0.01
"""A latent dimension is active when its mean moves across images: Var_x(E[z_d | x]) above
this (the activity measure of Burda et al., 2016, Importance Weighted Autoencoders). A
collapsed dimension keeps the prior's sigma near 1 and carries no information about the image."""

IMAGE_SHAPE = (3, 64, 64)
INITIAL_LOG_SIGMA = -3.0


class VAELoss(NamedTuple):
    total: torch.Tensor
    """reconstruction + beta * kl, per image, averaged over the batch."""
    reconstruction: torch.Tensor
    """Binary cross-entropy summed over the 3 x 64 x 64 pixels, per image."""
    kl: torch.Tensor
    """KL divergence of q(z|x) from N(0, I), per image."""


def to_input(images: np.ndarray | torch.Tensor) -> torch.Tensor:
    """uint8 observations (N, 64, 64, 3) to float input (N, 3, 64, 64) in [0, 1]."""
    x = torch.as_tensor(images)
    if x.dtype != torch.uint8 or x.shape[-3:] != (64, 64, 3):
        raise ValueError(f"expected uint8 images (..., 64, 64, 3), got {x.dtype} {tuple(x.shape)}")
    return x.movedim(-1, -3).float().div_(255.0)


class ConvVAE(nn.Module):
    """The World Models VAE with a ``latent_dim``-dimensional latent (the paper's 8)."""

    def __init__(self, latent_dim: int = 8) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 32, 4, stride=2), nn.ReLU(inplace=True),
            nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(inplace=True),
            nn.Conv2d(64, 128, 4, stride=2), nn.ReLU(inplace=True),
            nn.Conv2d(128, 256, 4, stride=2), nn.ReLU(inplace=True),
            nn.Flatten(),
        )  # fmt: skip
        self.fc_mu = nn.Linear(1024, latent_dim)
        self.fc_log_sigma = nn.Linear(1024, latent_dim)
        # Start with sigma ~ 0.05 rather than ~ 1: at initialization mu is small, and unit noise
        # would drown it, teaching the decoder to ignore z (the posterior collapses for
        # hundreds of updates). The KL term then grows sigma where z carries nothing.
        nn.init.constant_(self.fc_log_sigma.bias, INITIAL_LOG_SIGMA)
        nn.init.normal_(self.fc_log_sigma.weight, std=1e-3)
        self.fc_decode = nn.Linear(latent_dim, 1024)
        self.decoder = nn.Sequential(
            nn.Unflatten(1, (1024, 1, 1)),
            nn.ConvTranspose2d(1024, 128, 5, stride=2), nn.ReLU(),
            nn.ConvTranspose2d(128, 64, 5, stride=2), nn.ReLU(),
            nn.ConvTranspose2d(64, 32, 6, stride=2), nn.ReLU(),
            nn.ConvTranspose2d(32, 3, 6, stride=2),
        )  # fmt: skip

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mu, sigma) of q(z|x) for a batch of inputs (N, 3, 64, 64) in [0, 1]."""
        h = self.encoder(x)
        log_sigma = self.fc_log_sigma(h).clamp(-10.0, 5.0)
        return self.fc_mu(h), log_sigma.exp()

    def decode_logits(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.fc_decode(z))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Images (N, 3, 64, 64) in [0, 1] for latents (N, latent_dim)."""
        return torch.sigmoid(self.decode_logits(z))

    def forward(
        self, x: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reconstruction logits, mu and sigma, with z sampled by reparameterization."""
        mu, sigma = self.encode(x)
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        return self.decode_logits(mu + sigma * eps), mu, sigma

    def loss(
        self, x: torch.Tensor, beta: float, generator: torch.Generator | None = None
    ) -> VAELoss:
        """Equation (5) with beta: BCE summed over pixels plus beta * KL, per image."""
        logits, mu, sigma = self(x, generator)
        return vae_loss(logits, x, mu, sigma, beta)


def vae_loss(
    logits: torch.Tensor, x: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, beta: float
) -> VAELoss:
    reconstruction = (
        F.binary_cross_entropy_with_logits(logits, x, reduction="none").flatten(1).sum(1).mean()
    )
    kl = (-0.5 * (1 + 2 * sigma.log() - mu.square() - sigma.square())).sum(1).mean()
    return VAELoss(reconstruction + beta * kl, reconstruction, kl)


@torch.no_grad()
def encode_images(
    vae: ConvVAE, images: np.ndarray, batch_size: int = 1000
) -> tuple[torch.Tensor, torch.Tensor]:
    """(mu, sigma) for uint8 observations (N, 64, 64, 3), in batches, in eval mode.

    An image's latent does not depend on the batch it comes in: PyTorch's CPU convolution takes
    another path for a batch of one, whose results differ in the last bits (1e-7), enough to
    change a training run after hundreds of episodes; so a lone image is encoded beside a copy
    of itself. A population's agents then see what they would see alone."""
    was_training = vae.training
    vae.eval()
    mus, sigmas = [], []
    device = next(vae.parameters()).device
    for start in range(0, len(images), batch_size):
        chunk = images[start : start + batch_size]
        lone = len(chunk) == 1
        if lone:
            chunk = np.concatenate([chunk, chunk])
        mu, sigma = vae.encode(to_input(chunk).to(device))
        mus.append(mu[:1] if lone else mu)
        sigmas.append(sigma[:1] if lone else sigma)
    vae.train(was_training)
    return torch.cat(mus), torch.cat(sigmas)
