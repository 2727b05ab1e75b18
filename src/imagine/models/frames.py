"""Frames of any image environment for V (issue 17): observations of a random policy, resized
to V's 64 x 64 RGB input.

V is the paper's 64 x 64 x 3 beta-VAE; an environment's images of any size H x W x C are
resized (bilinear, antialiased) to 64 x 64, a grey channel repeated three times and an alpha
channel dropped (:func:`to_vae_images`). :func:`random_frames` collects the training images
``imagine vae train --env ENV_ID`` fits V on.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from imagine.envs.spec import EnvSpec, episode_seed, reset_ended

VAE_SIZE = 64


def to_vae_images(images: np.ndarray) -> np.ndarray:
    """uint8 (N, H, W, C) with C in 1, 3, 4 to uint8 (N, 64, 64, 3); unchanged if already so."""
    x = np.asarray(images)
    if x.dtype != np.uint8 or x.ndim != 4 or x.shape[-1] not in (1, 3, 4):
        raise ValueError(f"expected uint8 images (N, H, W, C), got {x.dtype} {x.shape}")
    x = x[..., :3] if x.shape[-1] == 4 else np.repeat(x, 3, -1) if x.shape[-1] == 1 else x
    if x.shape[1:3] == (VAE_SIZE, VAE_SIZE):
        return np.ascontiguousarray(x)
    t = torch.from_numpy(np.ascontiguousarray(x)).movedim(-1, 1).float()
    antialias = x.shape[1] > VAE_SIZE or x.shape[2] > VAE_SIZE
    t = F.interpolate(t, size=(VAE_SIZE, VAE_SIZE), mode="bilinear", antialias=antialias,
                      align_corners=False)  # fmt: skip
    return t.round().clamp(0, 255).to(torch.uint8).movedim(1, -1).numpy()


def random_frames(spec: EnvSpec, n: int, seed: int, copies: int = 16) -> np.ndarray:
    """``n`` observations (as the encoder reads them) of a uniform random policy, resized for
    V: uint8 (n, 64, 64, 3). Episode k of the collection starts from a seed drawn from
    (``seed``, k)."""
    rng = np.random.default_rng(seed)
    envs = spec.make_vector_env(copies)
    started = copies
    obs, info = envs.reset(seed=[episode_seed(seed, k) for k in range(copies)])
    frames: list[np.ndarray] = []
    held = 0
    while held < n:
        x, _ = spec.encoder_input(obs, info)
        frames.append(to_vae_images(x))
        held += len(x)
        obs, _, terminated, truncated, info = envs.step(rng.integers(spec.n_actions, size=copies))
        ended = terminated | truncated
        if ended.any():
            # the ended copies start episodes started, started + 1, ... in copy order
            obs, info = reset_ended(envs, ended, started + np.cumsum(ended) - 1, seed)
            started += int(ended.sum())
    envs.close()
    return np.concatenate(frames)[:n]
