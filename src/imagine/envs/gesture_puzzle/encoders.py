"""What C and M see: V's latent, or an oracle embedding of the true macrostate.

All encoders give ``(mu, sigma)`` for a batch of observations, read a macrostate back from a
latent (for M's accuracy), and give one reference latent per macrostate (the 192 states M's
accuracy is measured from). The oracle feeds C and M a fixed random embedding of the true
macrostate, so the learning of M and C can be tested and studied apart from vision.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from imagine.envs.gesture_puzzle.rules import all_macrostates, macrostate_index
from imagine.envs.gesture_puzzle.scene import SceneComposer
from imagine.models.vision import encode_images


def factored_embedding(states: np.ndarray) -> torch.Tensor:
    """An 8-dimensional embedding with one 2-D unit vector per factor: each arrow as the
    direction it points, (cos, sin) of d * 90 degrees, and the hand as (cos, sin) of
    h * 120 degrees. Rotating a cube rotates its vector, so the dynamics are as simple in this
    space as a disentangled V could make them."""
    s = torch.tensor(np.asarray(states), dtype=torch.float32)
    angles = torch.cat([s[..., :3] * (torch.pi / 2), s[..., 3:] * (2 * torch.pi / 3)], dim=-1)
    return torch.stack([angles.cos(), angles.sin()], dim=-1).flatten(-2)


class OracleEncoder:
    """A fixed embedding of the true macrostate (:func:`factored_embedding`); sigma is a small
    constant so latents can still be re-sampled as V's are."""

    latent_dim = 8

    def __init__(self, sigma: float = 0.05) -> None:
        self.sigma = sigma
        self.table = factored_embedding(all_macrostates())

    def encode(self, images: np.ndarray, states: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        mu = self.table[torch.as_tensor(macrostate_index(states))]
        return mu, torch.full_like(mu, self.sigma)

    def classify(self, z: torch.Tensor) -> torch.Tensor:
        """The macrostate of the nearest embedding, int64 (N, 4)."""
        nearest = torch.cdist(z, self.table).argmin(-1)
        return torch.from_numpy(all_macrostates().copy())[nearest]

    def state_latents(self) -> torch.Tensor:
        return self.table.clone()


class VaeEncoder:
    """V's posterior; macrostates are read back with the run's latent classifier."""

    observation_shape = (64, 64, 3)
    observation_dtype = "uint8"

    def __init__(
        self,
        run: str | Path,
        composer: SceneComposer,
        images_per_state: int = 8,
        device: str | torch.device = "cpu",
    ):
        from imagine.models.vision_training import load_classifier, load_vae

        self.vae, config, self.epoch = load_vae(run)
        self.vae.eval().to(device)
        self.latent_dim = config.latent_dim
        self.vision_config = config
        self.classifier = load_classifier(run, config.latent_dim)
        rng = np.random.default_rng(0)
        states = np.repeat(all_macrostates(), images_per_state, axis=0)
        mu, _ = encode_images(self.vae, composer.sample(rng, states))
        self._state_latents = mu.view(192, images_per_state, -1).mean(1).cpu()

    @torch.no_grad()
    def encode(self, images: np.ndarray, states: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        return encode_images(self.vae, images)

    def classify(self, z: torch.Tensor) -> torch.Tensor:
        return self.classifier.predict(z.cpu())

    def state_latents(self) -> torch.Tensor:
        return self._state_latents.clone()
