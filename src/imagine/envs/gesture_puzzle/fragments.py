"""Pools of image fragments, one pool per microstate (docs/design.md section 1; paper section V-A).

A :class:`FragmentPool` holds grayscale fragments for every cube-and-arrow microstate
``(cube i, direction d)`` and every hand microstate (the pointed cube ``h``). It comes from the
procedural renderer (:func:`procedural_pool`, the default) or from a folder of photographs
(:func:`load_fragment_folder`), laid out as::

    FOLDER/
      cube0/up/*.png   cube0/right/*.png   cube0/down/*.png   cube0/left/*.png
      cube1/...        cube2/...
      hand/cube0/*.png hand/cube1/*.png    hand/cube2/*.png

Every cube image has one size ``(H_c, W_c)``; every hand image is ``(H_h, 3 * W_c)``: the strip
under the three cubes, the hand pointing at the named cube. Images are read as grayscale
(PNG, JPEG, BMP or TIFF). Pools may hold different numbers of fragments per microstate.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from imagine.envs.gesture_puzzle.procedural import cube_fragment, hand_fragment
from imagine.envs.gesture_puzzle.rules import DIRECTION_NAMES, N_CUBES, N_DIRECTIONS
from imagine.errors import ConfigError, FragmentFolderError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True, eq=False)
class FragmentPool:
    """Fragments per microstate, padded to the largest pool, with the true counts beside them.

    Attributes:
        cubes: uint8 (3, 4, K_c, H_c, W_c): fragment k of cube i with its arrow in direction d.
        cube_counts: int64 (3, 4): how many of the K_c slots of (i, d) are real fragments.
        hands: uint8 (3, K_h, H_h, 3 * W_c): fragment k of the hand pointing at cube h.
        hand_counts: int64 (3,): how many of the K_h slots of h are real fragments.
    """

    cubes: np.ndarray
    cube_counts: np.ndarray
    hands: np.ndarray
    hand_counts: np.ndarray

    @property
    def cube_shape(self) -> tuple[int, int]:
        return self.cubes.shape[-2], self.cubes.shape[-1]

    @property
    def hand_shape(self) -> tuple[int, int]:
        return self.hands.shape[-2], self.hands.shape[-1]

    @property
    def scene_shape(self) -> tuple[int, int]:
        """(height, width) of a full scene: the three cubes side by side over the hand strip."""
        return self.cube_shape[0] + self.hand_shape[0], self.hand_shape[1]

    def sample_indices(self, rng: np.random.Generator, states: np.ndarray) -> np.ndarray:
        """One random fragment per microstate of each macrostate, with one draw from ``rng``.

        ``states`` has shape (..., 4); returns int64 (..., 4): the fragment of cubes 0..2 and
        of the hand.
        """
        s = np.asarray(states, dtype=np.int64)
        highs = np.concatenate(
            [self.cube_counts[np.arange(N_CUBES), s[..., :N_CUBES]], self.hand_counts[s[..., 3:]]],
            axis=-1,
        )
        return rng.integers(0, highs)


def _freeze(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@lru_cache(maxsize=8)
def procedural_pool(seed: int = 0, n_cube: int = 16, n_hand: int = 50) -> FragmentPool:
    """The built-in pool: ``n_cube`` fragments per (cube, direction) and ``n_hand`` per pointed
    cube (the paper's 16 and 50 by default), drawn deterministically from ``seed``."""
    if n_cube < 1 or n_hand < 1:
        raise ConfigError(
            f"fragment counts must be at least 1, got n_cube={n_cube}, n_hand={n_hand}"
        )
    cubes = np.stack(
        [
            np.stack(
                [
                    np.stack([cube_fragment(seed, i, d, k) for k in range(n_cube)])
                    for d in range(N_DIRECTIONS)
                ]
            )
            for i in range(N_CUBES)
        ]
    )
    hands = np.stack(
        [np.stack([hand_fragment(seed, h, k) for k in range(n_hand)]) for h in range(N_CUBES)]
    )
    cube_counts = np.full((N_CUBES, N_DIRECTIONS), n_cube, dtype=np.int64)
    hand_counts = np.full((N_CUBES,), n_hand, dtype=np.int64)
    _freeze(cubes, hands, cube_counts, hand_counts)
    return FragmentPool(cubes, cube_counts, hands, hand_counts)


# --- Folders of photographs ----------------------------------------------------------------------


def _microstate_dirs(root: Path) -> list[tuple[str, Path]]:
    """(label, folder) of every microstate in the documented layout, cubes first."""
    dirs = [
        (f"cube{i}/{name}", root / f"cube{i}" / name)
        for i in range(N_CUBES)
        for name in DIRECTION_NAMES
    ]
    return dirs + [(f"hand/cube{h}", root / "hand" / f"cube{h}") for h in range(N_CUBES)]


def _read_gray(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as img:
            return np.asarray(img.convert("L"), dtype=np.uint8)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise FragmentFolderError(f"cannot read fragment image {path}: {exc}") from None


def _read_pool(label: str, folder: Path, expected: tuple[int, int] | None) -> list[np.ndarray]:
    if not folder.is_dir():
        raise FragmentFolderError(f"fragment folder has no {label}/ folder (expected {folder})")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FragmentFolderError(
            f"fragment folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})"
        )
    images = []
    for path in files:
        img = _read_gray(path)
        shape = img.shape
        if expected is None:
            expected = shape
        if shape != expected:
            raise FragmentFolderError(
                f"fragment {path} is {shape[0]}x{shape[1]} (HxW); {label} fragments must be "
                f"{expected[0]}x{expected[1]}"
            )
        images.append(img)
    return images


def _pad_stack(pools: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Stack pools of unequal length into (n_pools, K_max, H, W), repeating the last fragment."""
    k_max = max(len(p) for p in pools)
    stacked = np.stack([np.stack(p + [p[-1]] * (k_max - len(p))) for p in pools])
    return stacked, np.array([len(p) for p in pools], dtype=np.int64)


def load_fragment_folder(folder: str | Path) -> FragmentPool:
    """Read a folder of fragment photographs (layout in the module docstring).

    Raises :class:`FragmentFolderError` with a one-line message for a missing folder, a missing
    or empty microstate folder, an unreadable image, or an image of the wrong size.
    """
    root = Path(folder)
    if not root.is_dir():
        raise FragmentFolderError(f"fragment folder {root} does not exist or is not a folder")
    cube_pools: list[list[np.ndarray]] = []
    cube_shape: tuple[int, int] | None = None
    hand_pools: list[list[np.ndarray]] = []
    hand_shape: tuple[int, int] | None = None
    for label, path in _microstate_dirs(root):
        if label.startswith("cube"):
            cube_pools.append(_read_pool(label, path, cube_shape))
            cube_shape = cube_pools[-1][0].shape
        else:
            hand_pools.append(_read_pool(label, path, hand_shape))
            hand_shape = hand_pools[-1][0].shape
    assert cube_shape is not None and hand_shape is not None
    if hand_shape[1] != N_CUBES * cube_shape[1]:
        raise FragmentFolderError(
            f"hand fragments are {hand_shape[1]} pixels wide; they must span the three cubes, "
            f"3 x {cube_shape[1]} = {N_CUBES * cube_shape[1]}"
        )
    cubes, cube_counts = _pad_stack(cube_pools)
    hands, hand_counts = _pad_stack(hand_pools)
    cubes = cubes.reshape(N_CUBES, N_DIRECTIONS, *cubes.shape[1:])
    cube_counts = cube_counts.reshape(N_CUBES, N_DIRECTIONS)
    _freeze(cubes, hands, cube_counts, hand_counts)
    return FragmentPool(cubes, cube_counts, hands, hand_counts)


def save_fragment_folder(pool: FragmentPool, folder: str | Path) -> Path:
    """Write ``pool`` as PNGs in the documented layout: a template for real photographs.
    Numbered PNGs left in a microstate folder by an earlier, larger export are removed, so the
    folder holds exactly the pool."""
    root = Path(folder)
    for label, path in _microstate_dirs(root):
        path.mkdir(parents=True, exist_ok=True)
        for stale in path.glob("[0-9][0-9][0-9].png"):
            stale.unlink()
        if label.startswith("cube"):
            i, d = int(label[4]), DIRECTION_NAMES.index(label.split("/")[1])
            images = pool.cubes[i, d, : pool.cube_counts[i, d]]
        else:
            h = int(label[-1])
            images = pool.hands[h, : pool.hand_counts[h]]
        for k, img in enumerate(images):
            Image.fromarray(img).save(path / f"{k:03d}.png")
    return root
