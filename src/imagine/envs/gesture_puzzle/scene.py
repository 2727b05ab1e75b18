"""Image synthesis: compose fragments into a scene and cut it into the observation.

Following the paper (section V-B, Variational Autoencoder), the grayscale scene is split along
the horizontal axis into 3 strips, one cube per strip; each strip is resized to 64 x 64 and the
three strips are stacked as the 3 channels of a uint8 (64, 64, 3) observation.

Resizing is linear (area averaging), so resizing a composed scene equals the sum of the resized
pieces it is composed of. :class:`SceneComposer` therefore resizes every fragment once, when it
is built, and an observation is then a gather and an add: 100,000 observations take seconds.
"""

from __future__ import annotations

import numpy as np

from imagine.envs.gesture_puzzle.fragments import FragmentPool
from imagine.envs.gesture_puzzle.rules import N_CUBES

OBS_SIZE = 64


def area_resize_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) matrix that resizes a 1-D signal by area averaging: output pixel j is the
    mean of the input over the interval it covers. Rows sum to one."""
    edges = np.linspace(0.0, n_in, n_out + 1)
    left, right = edges[:-1, None], edges[1:, None]
    pixel = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(right, pixel + 1) - np.maximum(left, pixel), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


_FRACTION_BITS = 8
_HALF = 1 << (_FRACTION_BITS - 1)


def _to_fixed(x: np.ndarray) -> np.ndarray:
    """Gray levels in [0, 255] as uint16 with 8 fractional bits (255.5 * 256 < 2**16)."""
    out = np.rint(x * (1 << _FRACTION_BITS)).astype(np.uint16)
    out.setflags(write=False)
    return out


class SceneComposer:
    """Makes observations and full scenes of macrostates from a :class:`FragmentPool`."""

    def __init__(self, pool: FragmentPool, obs_size: int = OBS_SIZE) -> None:
        self.pool = pool
        self.obs_size = obs_size
        (ch, cw), (hh, _) = pool.cube_shape, pool.hand_shape
        rows = area_resize_matrix(ch + hh, obs_size)  # (64, H) over a strip's height
        cols = area_resize_matrix(cw, obs_size).T  # (W_c, 64) over a strip's width
        top, bottom = rows[:, :ch], rows[:, ch:]
        # cube_parts[i, d, k]: fragment k of (cube i, direction d) as it appears in strip i.
        cube_parts = top @ pool.cubes.astype(np.float64) @ cols
        # hand_parts[h, k, i]: the part of hand fragment (h, k) that falls in strip i.
        hands = pool.hands.astype(np.float64).reshape(*pool.hands.shape[:3], N_CUBES, cw)
        hand_parts = bottom @ hands.transpose(0, 1, 3, 2, 4) @ cols
        # Fixed point with 8 fractional bits: a strip is two uint16 gathers and an add, ten
        # times faster than in float32, and within one gray level of resizing the full scene.
        self.cube_parts = _to_fixed(cube_parts)
        self.hand_parts = _to_fixed(hand_parts)

    def observe(self, states: np.ndarray, fragments: np.ndarray) -> np.ndarray:
        """Observations of macrostates ``states`` (..., 4) drawn with fragment indices
        ``fragments`` (..., 4) (see :meth:`FragmentPool.sample_indices`): uint8 (..., 64, 64, 3)."""
        s = np.asarray(states, dtype=np.int64)
        f = np.asarray(fragments, dtype=np.int64)
        n_dir, k_cube = self.cube_parts.shape[1:3]
        k_hand = self.hand_parts.shape[1]
        size = self.obs_size
        cubes = self.cube_parts.reshape(-1, size, size)  # flat row (i, d, k)
        hands = self.hand_parts.reshape(-1, size, size)  # flat row (h, k, i)
        out = np.empty((*s.shape[:-1], size, size, N_CUBES), dtype=np.uint8)
        for i in range(N_CUBES):
            # np.take on flat row numbers is twice as fast as multi-axis fancy indexing.
            strip = np.take(cubes, (i * n_dir + s[..., i]) * k_cube + f[..., i], axis=0)
            strip += np.take(hands, (s[..., 3] * k_hand + f[..., 3]) * N_CUBES + i, axis=0)
            strip += _HALF
            strip >>= _FRACTION_BITS
            out[..., i] = strip
        return out

    def sample(self, rng: np.random.Generator, states: np.ndarray) -> np.ndarray:
        """Observations of ``states`` with fragments drawn from ``rng``."""
        return self.observe(states, self.pool.sample_indices(rng, states))

    def scene(self, state: np.ndarray, fragments: np.ndarray) -> np.ndarray:
        """The full-resolution grayscale scene (H, W) of one macrostate, as the camera sees it."""
        s, f = np.asarray(state, dtype=np.int64), np.asarray(fragments, dtype=np.int64)
        cubes = [self.pool.cubes[i, s[i], f[i]] for i in range(N_CUBES)]
        return np.vstack([np.hstack(cubes), self.pool.hands[s[3], f[3]]])
