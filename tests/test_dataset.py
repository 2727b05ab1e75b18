"""`imagine dataset`: the synthesized images V trains on, written and read back safely."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imagine.envs.gesture_puzzle import rules
from imagine.envs.gesture_puzzle.dataset import (
    DatasetConfig,
    load_dataset,
    save_dataset,
    synthesize,
)
from imagine.errors import ConfigError, DatasetFileError

IMAGINE = str(Path(sys.executable).parent / "imagine")


def test_synthesize_round_trip_and_determinism(tmp_path):
    config = DatasetConfig(n_train=600, n_test=200, seed=3)
    arrays = synthesize(config, chunk=256)
    assert arrays["train_images"].shape == (600, 64, 64, 3)
    assert arrays["test_images"].dtype == np.uint8
    assert arrays["test_macrostates"].shape == (200, 4)
    seen = {tuple(s) for s in arrays["train_macrostates"]}
    assert len(seen) > 180  # uniform over all 192 macrostates, illegal and goal included
    assert rules.is_illegal(arrays["train_macrostates"]).any()
    assert not np.array_equal(arrays["train_images"][:200], arrays["test_images"])
    again = synthesize(config, chunk=1000)  # chunking does not change the images
    for key in arrays:
        assert np.array_equal(arrays[key], again[key])
    path = save_dataset(tmp_path / "d.safetensors", arrays, config)
    loaded, loaded_config = load_dataset(path)
    assert loaded_config == config
    for key in arrays:
        assert np.array_equal(arrays[key], loaded[key])
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_images_match_their_macrostates():
    """The same macrostate drawn twice shares its arrows, not its pixels; a different
    arrow changes the image of that cube's channel far more than fragment variation."""
    arrays = synthesize(DatasetConfig(n_train=3000, n_test=1, seed=0))
    images = arrays["train_images"].astype(np.float64)
    states = arrays["train_macrostates"]
    up = images[states[:, 0] == rules.UP, :40, :, 0].mean(axis=0)
    down = images[states[:, 0] == rules.DOWN, :40, :, 0].mean(axis=0)
    # An arrow pointing up is dark above the cube's centre, one pointing down below it.
    assert up[8:20].mean() < down[8:20].mean() and up[24:36].mean() > down[24:36].mean()


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "does not exist"),
        (b"not a safetensors file at all", "not a readable safetensors dataset"),
    ],
)
def test_bad_dataset_files(tmp_path, content, message):
    path = tmp_path / "bad.safetensors"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DatasetFileError, match=message):
        load_dataset(path)


def test_truncated_and_foreign_files(tmp_path):
    config = DatasetConfig(n_train=20, n_test=5)
    path = save_dataset(tmp_path / "d.safetensors", synthesize(config), config)
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(DatasetFileError, match="not a readable safetensors dataset"):
        load_dataset(cut)
    from safetensors.numpy import save_file

    foreign = tmp_path / "foreign.safetensors"
    save_file({"x": np.zeros(3, dtype=np.float32)}, str(foreign))
    with pytest.raises(DatasetFileError, match="not an imagine dataset"):
        load_dataset(foreign)


def test_bad_config():
    with pytest.raises(ConfigError, match="must be positive"):
        DatasetConfig(n_train=0)


def test_dataset_command(tmp_path):
    out = tmp_path / "vae.safetensors"
    done = subprocess.run(
        [IMAGINE, "dataset", str(out), "--n-train", "300", "--n-test", "100"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "images/s" in done.stderr
    arrays, config = load_dataset(out)
    assert len(arrays["train_images"]) == 300 and config.n_test == 100


def test_metadata_that_does_not_match_the_arrays(tmp_path):
    import json

    from safetensors.numpy import save_file

    config = DatasetConfig(n_train=10, n_test=2)
    arrays = synthesize(config)
    meta = {"imagine_dataset": json.dumps({"n_train": 100, "n_test": 2})}
    save_file(arrays, str(tmp_path / "a.safetensors"), metadata=meta)
    with pytest.raises(DatasetFileError, match="metadata says 100"):
        load_dataset(tmp_path / "a.safetensors")
    arrays["test_macrostates"][0, 0] = 9
    save_file(arrays, str(tmp_path / "b.safetensors"),
              metadata={"imagine_dataset": json.dumps({"n_train": 10, "n_test": 2})})  # fmt: skip
    with pytest.raises(DatasetFileError, match="not valid"):
        load_dataset(tmp_path / "b.safetensors")
    save_file(arrays, str(tmp_path / "c.safetensors"), metadata={"imagine_dataset": "{oops"})
    with pytest.raises(DatasetFileError, match="unreadable dataset metadata"):
        load_dataset(tmp_path / "c.safetensors")
