"""The Encoder protocol, and the encoders of observations that need no V.

An encoder turns a batch of observations into the posterior C and M work in: ``(mu, sigma)``,
float32 (N, latent_dim) each. V is one (:class:`~imagine.envs.gesture_puzzle.encoders.VaeEncoder`,
images); the paper's task also has an oracle of its true state
(:class:`~imagine.envs.gesture_puzzle.encoders.OracleEncoder`). For any other Gymnasium environment
(:mod:`imagine.envs.gym`) the observation space decides: a vector passes as it is
(:class:`VectorEncoder`), a Discrete observation as its one-hot vector (:class:`OneHotEncoder`), an
image through a V trained on that environment's frames. The encoders here are exact, so their sigma
is 0: M's re-sampled inputs are the observation itself.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch


class Encoder(Protocol):
    """What C and M see of an observation."""

    latent_dim: int

    def encode(self, observations: Any, extra: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mu, sigma)``, float32 (N, latent_dim), for N observations; ``extra`` is what the
        environment's spec hands beside them (GesturePuzzle's true macrostates, else None)."""
        ...


class VectorEncoder:
    """A Box observation that is not an image as the latent itself (mu = obs, sigma = 0): a
    1-D vector as it is, a grid (MinAtar's 10 x 10 x n booleans) flattened in C order."""

    def __init__(self, shape: int | tuple[int, ...]) -> None:
        self.observation_shape = (int(shape),) if isinstance(shape, int) else tuple(shape)
        """One observation's shape (``Agent.act`` checks what it is given against it)."""
        self.observation_ndim = len(self.observation_shape)
        self.latent_dim = int(np.prod(self.observation_shape))

    def encode(self, observations: Any, extra: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        mu = torch.as_tensor(np.asarray(observations, dtype=np.float32)).reshape(
            -1, self.latent_dim
        )
        return mu, torch.zeros_like(mu)


class OneHotEncoder:
    """A Discrete observation as its one-hot vector (sigma = 0)."""

    observation_ndim = 0
    observation_shape = ()
    observation_dtype = "integer"

    def __init__(self, n: int) -> None:
        self.latent_dim = int(n)

    def encode(self, observations: Any, extra: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.as_tensor(np.asarray(observations, dtype=np.int64)).reshape(-1)
        mu = torch.nn.functional.one_hot(index, self.latent_dim).float()
        return mu, torch.zeros_like(mu)


class ImageEncoder:
    """V's posterior of another environment's images (resized to V's 64 x 64 RGB,
    :func:`imagine.models.frames.to_vae_images`); V from ``imagine vae train --env``."""

    observation_ndim = 3
    observation_shape = ("H", "W", "C")
    """Any height and width (resized for V), C in 1, 3 or 4 channels."""
    observation_dtype = "uint8"

    def __init__(self, run, device: str | torch.device = "cpu") -> None:
        from imagine.models.vision_training import load_vae

        self.vae, config, self.epoch = load_vae(run)
        self.vae.eval().to(device)
        self.latent_dim = config.latent_dim
        self.vision_config = config

    @torch.no_grad()
    def encode(self, observations: Any, extra: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        from imagine.models.frames import to_vae_images
        from imagine.models.vision import encode_images

        return encode_images(self.vae, to_vae_images(observations))
