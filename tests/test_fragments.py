"""Fragment pools: the procedural renderer, folders of photographs, and the scene composer."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from imagine.envs.gesture_puzzle import (
    FragmentPool,
    GesturePuzzleEnv,
    SceneComposer,
    load_fragment_folder,
    procedural_pool,
    rules,
    save_fragment_folder,
    transition,
)
from imagine.envs.gesture_puzzle.procedural import CUBE_SHAPE, HAND_SHAPE
from imagine.envs.gesture_puzzle.rules import (
    DIRECTION_NAMES,
    N_CUBES,
    N_DIRECTIONS,
    all_macrostates,
)
from imagine.envs.gesture_puzzle.scene import OBS_SIZE, area_resize_matrix
from imagine.errors import ConfigError, FragmentFolderError

# Small pools keep the tests fast: N_CUBE fragments per (cube, direction), N_HAND per hand.
N_CUBE, N_HAND = 3, 5
IMAGINE = Path(sys.executable).parent / "imagine"


def assert_same_pool(a: FragmentPool, b: FragmentPool) -> None:
    np.testing.assert_array_equal(a.cubes, b.cubes)
    np.testing.assert_array_equal(a.cube_counts, b.cube_counts)
    np.testing.assert_array_equal(a.hands, b.hands)
    np.testing.assert_array_equal(a.hand_counts, b.hand_counts)


@pytest.fixture(scope="module")
def small_pool() -> FragmentPool:
    return procedural_pool(0, N_CUBE, N_HAND)


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory, small_pool: FragmentPool) -> Path:
    """A good fragment folder, written once; tests copy it before changing it."""
    return save_fragment_folder(small_pool, tmp_path_factory.mktemp("template") / "fragments")


@pytest.fixture
def folder(tmp_path: Path, template: Path) -> Path:
    """A private copy of the good folder, free to damage."""
    return Path(shutil.copytree(template, tmp_path / "fragments"))


# --- The procedural pool ---------------------------------------------------------------------


def test_procedural_pool_default_shapes_and_dtypes() -> None:
    pool = procedural_pool()
    assert pool.cubes.shape == (N_CUBES, N_DIRECTIONS, 16, *CUBE_SHAPE) == (3, 4, 16, 96, 96)
    assert pool.hands.shape == (N_CUBES, 50, *HAND_SHAPE) == (3, 50, 48, 288)
    assert pool.cubes.dtype == pool.hands.dtype == np.uint8
    np.testing.assert_array_equal(pool.cube_counts, np.full((3, 4), 16))
    np.testing.assert_array_equal(pool.hand_counts, np.full(3, 50))
    assert pool.cube_shape == (96, 96)
    assert pool.hand_shape == (48, 288)
    assert pool.scene_shape == (144, 288)
    # The pool is shared through a cache: nobody may write into it.
    for array in (pool.cubes, pool.hands, pool.cube_counts, pool.hand_counts):
        assert not array.flags.writeable


def test_procedural_pool_is_deterministic_for_a_seed(small_pool: FragmentPool) -> None:
    # Bypass the cache, or "the same seed gives the same arrays" would be trivially true.
    assert_same_pool(procedural_pool.__wrapped__(0, N_CUBE, N_HAND), small_pool)
    other = procedural_pool(1, N_CUBE, N_HAND)
    assert not np.array_equal(other.cubes, small_pool.cubes)
    assert not np.array_equal(other.hands, small_pool.hands)


def test_procedural_fragments_vary_within_a_microstate(small_pool: FragmentPool) -> None:
    # Fragments of one microstate differ (jitter, lighting, noise), and microstates differ.
    assert not np.array_equal(small_pool.cubes[0, 0, 0], small_pool.cubes[0, 0, 1])
    assert not np.array_equal(small_pool.cubes[0, 0, 0], small_pool.cubes[0, 1, 0])
    assert not np.array_equal(small_pool.hands[0, 0], small_pool.hands[0, 1])
    assert not np.array_equal(small_pool.hands[0, 0], small_pool.hands[1, 0])


def test_fragment_does_not_change_when_the_pool_grows() -> None:
    small, large = procedural_pool(0, 4, 5), procedural_pool(0, 16, 50)
    np.testing.assert_array_equal(small.cubes, large.cubes[:, :, :4])
    np.testing.assert_array_equal(small.hands, large.hands[:, :5])


@pytest.mark.parametrize(("n_cube", "n_hand"), [(0, 5), (3, 0), (-1, -1)])
def test_procedural_pool_rejects_empty_pools(n_cube: int, n_hand: int) -> None:
    with pytest.raises(ConfigError, match="at least 1"):
        procedural_pool(0, n_cube, n_hand)


# --- Folders: good ones ------------------------------------------------------------------------


def test_saved_folder_has_the_documented_layout(template: Path) -> None:
    for i in range(N_CUBES):
        for name in DIRECTION_NAMES:
            assert len(list((template / f"cube{i}" / name).glob("*.png"))) == N_CUBE
        assert len(list((template / "hand" / f"cube{i}").glob("*.png"))) == N_HAND


def test_folder_round_trip(template: Path, small_pool: FragmentPool) -> None:
    loaded = load_fragment_folder(template)
    assert_same_pool(loaded, small_pool)
    assert loaded.cubes.dtype == loaded.hands.dtype == np.uint8
    assert loaded.cube_shape == small_pool.cube_shape
    assert loaded.hand_shape == small_pool.hand_shape
    assert not loaded.cubes.flags.writeable and not loaded.hands.flags.writeable
    assert_same_pool(load_fragment_folder(str(template)), small_pool)  # a str works too


def test_folder_reads_color_and_other_formats_as_gray(folder: Path) -> None:
    path = folder / "cube2" / "left" / "000.png"
    gray = np.asarray(Image.open(path))
    Image.fromarray(np.repeat(gray[..., None], 3, axis=-1)).save(path)  # RGB, same gray level
    Image.fromarray(gray).save(path.with_suffix(".BMP"))  # another format, upper-case suffix
    (folder / "cube2" / "left" / "README.txt").write_text("not an image, ignored")
    pool = load_fragment_folder(folder)
    assert pool.cube_counts[2, DIRECTION_NAMES.index("left")] == N_CUBE + 1
    np.testing.assert_array_equal(pool.cubes[2, 3, 0], gray)


def test_folder_with_unequal_counts(folder: Path, small_pool: FragmentPool) -> None:
    keep = {("cube0", "up"): 1, ("cube2", "left"): 2, ("hand", "cube1"): 2, ("hand", "cube2"): 1}
    for (a, b), n in keep.items():
        for path in sorted((folder / a / b).glob("*.png"))[n:]:
            path.unlink()
    pool = load_fragment_folder(folder)

    cube_counts = np.full((3, 4), N_CUBE)
    cube_counts[0, 0], cube_counts[2, 3] = 1, 2
    np.testing.assert_array_equal(pool.cube_counts, cube_counts)
    np.testing.assert_array_equal(pool.hand_counts, [N_HAND, 2, 1])
    # Padded to the largest pool; the real slots are the files that are left.
    assert pool.cubes.shape == small_pool.cubes.shape
    assert pool.hands.shape == small_pool.hands.shape
    for i in range(N_CUBES):
        for d in range(N_DIRECTIONS):
            n = cube_counts[i, d]
            np.testing.assert_array_equal(pool.cubes[i, d, :n], small_pool.cubes[i, d, :n])
        n = pool.hand_counts[i]
        np.testing.assert_array_equal(pool.hands[i, :n], small_pool.hands[i, :n])

    # sample_indices stays within each microstate's real fragments, and reaches all of them.
    rng = np.random.default_rng(0)
    states = all_macrostates()[rng.integers(0, len(all_macrostates()), size=20_000)]
    idx = pool.sample_indices(rng, states)
    assert idx.shape == (20_000, 4) and idx.dtype == np.int64
    highs = np.concatenate(
        [pool.cube_counts[np.arange(3), states[:, :3]], pool.hand_counts[states[:, 3:]]], axis=1
    )
    assert (idx >= 0).all()
    assert (idx < highs).all()
    for i, d in [(0, 0), (2, 3), (1, 1)]:
        seen = idx[states[:, i] == d, i]
        assert set(seen.tolist()) == set(range(cube_counts[i, d]))
    for h in range(N_CUBES):
        assert set(idx[states[:, 3] == h, 3].tolist()) == set(range(pool.hand_counts[h]))


def test_sample_indices_keeps_the_batch_shape(small_pool: FragmentPool) -> None:
    rng = np.random.default_rng(1)
    assert small_pool.sample_indices(rng, np.array([0, 1, 2, 0])).shape == (4,)
    assert small_pool.sample_indices(rng, np.zeros((2, 5, 4), dtype=np.int64)).shape == (2, 5, 4)


# --- Folders: bad ones -------------------------------------------------------------------------


def _gray(shape: tuple[int, int]) -> Image.Image:
    return Image.fromarray(np.full(shape, 128, dtype=np.uint8))


def _no_folder(root: Path) -> Path:
    return root.parent / "does-not-exist"


def _a_file(root: Path) -> Path:
    path = root.parent / "fragments.png"
    path.write_bytes(b"not a folder")
    return path


def _remove_microstate(root: Path) -> Path:
    shutil.rmtree(root / "cube1" / "left")
    return root


def _remove_hand_microstate(root: Path) -> Path:
    shutil.rmtree(root / "hand" / "cube2")
    return root


def _empty_microstate(root: Path) -> Path:
    for path in (root / "cube2" / "down").iterdir():
        path.unlink()
    return root


def _only_non_images(root: Path) -> Path:
    for path in (root / "hand" / "cube0").iterdir():
        path.unlink()
    (root / "hand" / "cube0" / "notes.txt").write_text("hello")
    return root


def _garbage_png(root: Path) -> Path:
    (root / "cube0" / "right" / "001.png").write_bytes(b"\x00garbage, not a PNG" * 10)
    return root


def _truncated_png(root: Path) -> Path:
    path = root / "hand" / "cube1" / "002.png"
    path.write_bytes(path.read_bytes()[:200])
    return root


def _wrong_cube_size(root: Path) -> Path:
    _gray((90, 96)).save(root / "cube1" / "up" / "002.png")
    return root


def _wrong_cube_size_whole_microstate(root: Path) -> Path:
    for path in (root / "cube2" / "left").iterdir():
        _gray((64, 64)).save(path)
    return root


def _wrong_hand_size(root: Path) -> Path:
    _gray((40, 288)).save(root / "hand" / "cube1" / "003.png")
    return root


def _hands_not_three_cubes_wide(root: Path) -> Path:
    for h in range(N_CUBES):
        for path in (root / "hand" / f"cube{h}").iterdir():
            _gray((48, 280)).save(path)
    return root


BAD_FOLDERS: list[tuple[str, Callable[[Path], Path], str]] = [
    ("no-folder", _no_folder, "does not exist or is not a folder"),
    ("a-file", _a_file, "does not exist or is not a folder"),
    ("missing-microstate", _remove_microstate, "has no cube1/left/ folder"),
    ("missing-hand-microstate", _remove_hand_microstate, "has no hand/cube2/ folder"),
    ("empty-microstate", _empty_microstate, "holds no images"),
    ("only-non-images", _only_non_images, "holds no images"),
    ("garbage-png", _garbage_png, "cannot read fragment image"),
    ("truncated-png", _truncated_png, "cannot read fragment image"),
    ("wrong-cube-size", _wrong_cube_size, "is 90x96 (HxW); cube1/up fragments must be 96x96"),
    (
        "wrong-cube-size-whole-microstate",
        _wrong_cube_size_whole_microstate,
        "is 64x64 (HxW); cube2/left fragments must be 96x96",
    ),
    ("wrong-hand-size", _wrong_hand_size, "is 40x288 (HxW); hand/cube1 fragments must be 48x288"),
    ("hands-not-3x-wide", _hands_not_three_cubes_wide, "3 x 96 = 288"),
]


@pytest.mark.parametrize(
    ("damage", "message"), [(d, m) for _, d, m in BAD_FOLDERS], ids=[i for i, _, _ in BAD_FOLDERS]
)
def test_bad_folder_raises_fragment_folder_error(
    folder: Path, damage: Callable[[Path], Path], message: str
) -> None:
    bad = damage(folder)
    with pytest.raises(FragmentFolderError) as info:
        load_fragment_folder(bad)
    text = str(info.value)
    assert message in text
    assert "\n" not in text  # one line, for the command line


def test_bad_image_error_names_the_file(folder: Path) -> None:
    _garbage_png(folder)
    with pytest.raises(FragmentFolderError, match=r"cube0/right/001\.png"):
        load_fragment_folder(folder)


def test_bad_folder_error_is_also_a_user_error() -> None:
    from imagine.errors import ImagineError

    assert issubclass(FragmentFolderError, ImagineError)


# --- The environment and the command line with a folder --------------------------------------


@pytest.mark.parametrize("as_str", [False, True])
def test_env_accepts_a_folder(template: Path, small_pool: FragmentPool, as_str: bool) -> None:
    env = GesturePuzzleEnv(fragments=str(template) if as_str else template)
    assert_same_pool(env.composer.pool, small_pool)
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3)
    assert env.observation_space.contains(obs)
    for a in range(6):
        state = info["macrostate"]
        obs, reward, terminated, truncated, info = env.step(a)
        assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3)
        assert info["macrostate"] == transition(state, a)
        assert reward == rules.rewards(np.array(info["macrostate"]), "original")
        if terminated or truncated:
            obs, info = env.reset()
            assert obs.dtype == np.uint8 and obs.shape == (64, 64, 3)


def test_env_with_a_bad_folder_raises(folder: Path) -> None:
    _remove_microstate(folder)
    with pytest.raises(FragmentFolderError):
        GesturePuzzleEnv(fragments=folder)


def test_env_rejects_a_bad_fragment_source() -> None:
    with pytest.raises(ConfigError, match="fragments must be"):
        GesturePuzzleEnv(fragments=42)  # type: ignore[arg-type]


def _run_show(fragments: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(IMAGINE), "env", "show", "--fragments", str(fragments), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=out.parent,
    )


def test_cli_bad_folder_prints_one_error_line(folder: Path, tmp_path: Path) -> None:
    _remove_microstate(folder)
    out = tmp_path / "sheet.png"
    result = _run_show(folder, out)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("error:")
    assert "has no cube1/left/ folder" in lines[0]
    assert str(folder) in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("name", ["photos[v2]", "shots[/2024]"])
def test_cli_error_line_keeps_square_brackets(tmp_path: Path, name: str) -> None:
    missing = tmp_path / name
    result = _run_show(missing, tmp_path / "sheet.png")
    assert result.returncode == 2, result.stderr
    lines = (result.stdout + result.stderr).strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("error:")
    assert str(missing) in lines[0]


# --- The scene composer --------------------------------------------------------------------


@pytest.mark.parametrize(("n_in", "n_out"), [(4, 2), (3, 2), (96, 64), (144, 64), (10, 64), (7, 7)])
def test_area_resize_matrix_rows_sum_to_one_and_keep_constants(n_in: int, n_out: int) -> None:
    m = area_resize_matrix(n_in, n_out)
    assert m.shape == (n_out, n_in)
    assert (m >= 0).all()
    np.testing.assert_allclose(m.sum(axis=1), 1.0)
    np.testing.assert_allclose(m @ np.full(n_in, 173.0), 173.0)
    # Every input pixel counts as much as every other: the columns carry equal total weight.
    np.testing.assert_allclose(m.sum(axis=0), n_out / n_in)


def test_area_resize_matrix_known_values() -> None:
    np.testing.assert_allclose(area_resize_matrix(4, 2), [[0.5, 0.5, 0, 0], [0, 0, 0.5, 0.5]])
    np.testing.assert_allclose(area_resize_matrix(3, 2), [[2 / 3, 1 / 3, 0], [0, 1 / 3, 2 / 3]])
    np.testing.assert_allclose(area_resize_matrix(5, 5), np.eye(5))
    image = np.arange(12.0).reshape(3, 4)
    resized = area_resize_matrix(3, 1) @ image @ area_resize_matrix(4, 2).T
    np.testing.assert_allclose(resized, [[image[:, :2].mean(), image[:, 2:].mean()]])


def _random_pool(seed: int, cube: tuple[int, int], hand_h: int, k_c: int, k_h: int):
    """A pool of noise with awkward sizes: every resize weight is fractional."""
    rng = np.random.default_rng(seed)
    cubes = rng.integers(0, 256, (3, 4, k_c, *cube), dtype=np.uint8)
    hands = rng.integers(0, 256, (3, k_h, hand_h, 3 * cube[1]), dtype=np.uint8)
    return FragmentPool(
        cubes, np.full((3, 4), k_c, dtype=np.int64), hands, np.full(3, k_h, dtype=np.int64)
    )


def _resized_strips(scene: np.ndarray, cube_w: int) -> np.ndarray:
    rows = area_resize_matrix(scene.shape[0], OBS_SIZE)
    cols = area_resize_matrix(cube_w, OBS_SIZE)
    strips = [scene[:, i * cube_w : (i + 1) * cube_w].astype(np.float64) for i in range(3)]
    return np.stack([rows @ s @ cols.T for s in strips], axis=-1)


@pytest.mark.parametrize(
    "make_pool",
    [
        lambda: procedural_pool(0, N_CUBE, N_HAND),
        lambda: _random_pool(0, (37, 53), 11, 2, 3),
        lambda: _random_pool(1, (150, 70), 70, 1, 2),
        lambda: _random_pool(2, (20, 30), 12, 2, 2),
    ],
    ids=["procedural", "noise-37x53", "noise-150x70", "noise-upsampled"],
)
def test_observation_is_the_scene_cut_and_resized(make_pool: Callable[[], FragmentPool]) -> None:
    pool = make_pool()
    composer = SceneComposer(pool)
    rng = np.random.default_rng(0)
    states = all_macrostates()[rng.integers(0, 192, size=24)]
    frags = pool.sample_indices(rng, states)
    batch = composer.observe(states, frags)
    assert batch.shape == (24, 64, 64, 3) and batch.dtype == np.uint8
    for state, frag, obs in zip(states, frags, batch, strict=True):
        scene = composer.scene(state, frag)
        assert scene.shape == pool.scene_shape
        np.testing.assert_array_equal(
            scene[: pool.cube_shape[0], : pool.cube_shape[1]], pool.cubes[0, state[0], frag[0]]
        )
        np.testing.assert_array_equal(scene[pool.cube_shape[0] :], pool.hands[state[3], frag[3]])
        expected = _resized_strips(scene, pool.cube_shape[1])
        assert np.abs(obs.astype(np.float64) - np.rint(expected)).max() <= 1
        np.testing.assert_array_equal(composer.observe(state, frag), obs)  # unbatched too


@pytest.mark.parametrize("level", [0, 255])
def test_observation_of_a_flat_scene_is_flat(level: int) -> None:
    # Full white must not overflow the fixed-point sum; black must stay black.
    pool = _random_pool(0, (37, 53), 11, 1, 1)
    flat = FragmentPool(
        np.full_like(pool.cubes, level),
        pool.cube_counts,
        np.full_like(pool.hands, level),
        pool.hand_counts,
    )
    composer = SceneComposer(flat)
    states = all_macrostates()
    obs = composer.observe(states, np.zeros_like(states))
    assert (obs == level).all()


def test_sample_draws_fragments_from_the_rng(small_pool: FragmentPool) -> None:
    composer = SceneComposer(small_pool)
    states = all_macrostates()[:10]
    a = composer.sample(np.random.default_rng(5), states)
    b = composer.observe(states, small_pool.sample_indices(np.random.default_rng(5), states))
    np.testing.assert_array_equal(a, b)
