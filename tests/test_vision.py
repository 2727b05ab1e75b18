"""V, the beta-VAE: shapes, the loss, training, checkpoints and the latent classifier."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from imagine.config import vision_preset
from imagine.envs.gesture_puzzle.dataset import DatasetConfig, synthesize
from imagine.envs.gesture_puzzle.latent_classifier import LatentClassifier
from imagine.errors import CheckpointError, ConfigError
from imagine.metrics import read_metrics
from imagine.models.vision import ConvVAE, encode_images, to_input, vae_loss
from imagine.models.vision_training import load_vae, train_vae

IMAGINE = str(Path(sys.executable).parent / "imagine")


@pytest.fixture(scope="module")
def images():
    arrays = synthesize(DatasetConfig(n_train=64, n_test=16, seed=5))
    return arrays["train_images"], arrays["train_macrostates"]


def test_encode_decode_shapes(images):
    vae = ConvVAE(latent_dim=8)
    x = to_input(images[0][:5])
    assert x.shape == (5, 3, 64, 64) and float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    with torch.no_grad():
        mu, sigma = vae.encode(x)
        out = vae.decode(mu)
    assert mu.shape == (5, 8) and sigma.shape == (5, 8) and (sigma > 0).all()
    assert out.shape == (5, 3, 64, 64) and float(out.min()) >= 0 and float(out.max()) <= 1
    one, _ = vae.encode(x[:1])  # a batch of one works too
    assert one.shape == (1, 8)
    with pytest.raises(ValueError, match="uint8"):
        to_input(np.zeros((2, 64, 64, 3), dtype=np.float32))


def test_loss_matches_the_formula_on_a_hand_computed_case():
    x = torch.tensor([[0.0, 1.0, 0.5]])
    logits = torch.tensor([[0.0, 0.0, 0.0]])  # predicts 0.5 everywhere
    mu, sigma = torch.tensor([[1.0, 0.0]]), torch.tensor([[1.0, 0.5]])
    loss = vae_loss(logits, x, mu, sigma, beta=4.0)
    assert float(loss.reconstruction) == pytest.approx(3 * np.log(2), rel=1e-6)
    kl = 0.5 * (1 + 0) + (-0.5 * (1 + 2 * np.log(0.5) - 0.25))  # per dimension, summed
    assert float(loss.kl) == pytest.approx(kl, rel=1e-6)
    assert float(loss.total) == pytest.approx(3 * np.log(2) + 4 * kl, rel=1e-6)


def test_loss_falls_over_sixty_steps(images):
    torch.manual_seed(0)
    vae = ConvVAE(8).to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(vae.parameters(), lr=1e-3)
    x = to_input(images[0][:16]).contiguous(memory_format=torch.channels_last)
    generator = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(60):
        loss = vae.loss(x, beta=4.0, generator=generator)
        optimizer.zero_grad()
        loss.total.backward()
        optimizer.step()
        losses.append(float(loss.total.detach()))
    assert np.mean(losses[-10:]) < 0.9 * np.mean(losses[:10])


def smoke(tmp_path, **overrides):
    config = vision_preset("smoke", **overrides)
    train_vae(config, tmp_path)
    return config


def test_training_writes_a_run_that_loads_to_the_same_outputs(tmp_path, images):
    smoke(tmp_path)
    for name in ("vae.safetensors", "vae.json", "classifier.safetensors", "metrics.csv",
                 "config.yaml"):  # fmt: skip
        assert (tmp_path / name).is_file(), name
    rows = (tmp_path / "metrics.csv").read_text().splitlines()
    assert len(rows) == 3 and "test/kl" in rows[0] and "train/reconstruction" in rows[0]
    vae, config, epoch = load_vae(tmp_path)
    again, _, _ = load_vae(tmp_path)
    assert epoch == 2 and config.latent_dim == 8
    a, _ = encode_images(vae, images[0][:8])
    b, _ = encode_images(again, images[0][:8])
    assert torch.equal(a, b)


def test_resume_continues_where_it_stopped(tmp_path):
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    smoke(straight, epochs=2)
    smoke(resumed, epochs=1)
    smoke(resumed, epochs=2)  # picks up after epoch 1
    a, _, _ = load_vae(straight)
    b, _, _ = load_vae(resumed)
    for (name, p), q in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(p, q), name

    def numbers(folder):  # every metric but wall-clock times
        return [{k: v for k, v in row.items() if not k.startswith("time/")}
                for row in read_metrics(folder / "metrics.csv")]  # fmt: skip

    assert numbers(resumed) == numbers(straight) and len(numbers(resumed)) == 2


def test_bad_checkpoints_get_clear_errors(tmp_path):
    smoke(tmp_path / "run")
    run = tmp_path / "run"
    other = tmp_path / "other"
    smoke(other, latent_dim=4)
    # A checkpoint of latent size 4 under metadata that says 8.
    (run / "vae.safetensors").write_bytes((other / "vae.safetensors").read_bytes())
    with pytest.raises(CheckpointError, match=r"does not fit this architecture.*fc_mu"):
        load_vae(run)
    data = (other / "vae.safetensors").read_bytes()
    (run / "vae.safetensors").write_bytes(data[: len(data) // 3])
    with pytest.raises(CheckpointError, match="corrupt or not safetensors"):
        load_vae(run)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_vae(tmp_path / "nowhere")
    (run / "vae.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_vae(run)


def test_a_run_folder_with_another_config_is_not_resumed(tmp_path):
    smoke(tmp_path, epochs=1)
    with pytest.raises(CheckpointError, match=r"another config \(beta 4\.0 -> 1\.0\)"):
        smoke(tmp_path, epochs=2, beta=1.0)  # the field named, old -> new


def test_bad_configs():
    with pytest.raises(ConfigError, match="did you mean 'latent_dim'"):
        vision_preset("fast", latent_dims=4)
    with pytest.raises(ConfigError, match=r"larger than vision\.n_train"):
        vision_preset("smoke", batch_size=10_000)
    with pytest.raises(ConfigError, match="unknown preset 'quick'"):
        vision_preset("quick")
    with pytest.raises(ConfigError, match="must be of type int"):
        vision_preset("fast", epochs="ten")


def test_classifier_is_right_on_the_latents_it_was_fit_on():
    """Latents of 192 macrostates as separated clusters (as a trained V gives them)."""
    from imagine.envs.gesture_puzzle.rules import all_macrostates

    rng = np.random.default_rng(0)
    states = all_macrostates()[rng.integers(0, 192, 2000)]
    centres = torch.randn(192, 8, generator=torch.Generator().manual_seed(0)) * 3
    index = torch.as_tensor(states[:, 0] * 48 + states[:, 1] * 12 + states[:, 2] * 3 + states[:, 3])
    z = centres[index] + 0.05 * torch.randn(2000, 8)
    classifier = LatentClassifier(8)
    losses = classifier.fit(z, torch.as_tensor(states), steps=800)
    assert losses[-1] < 0.05 * losses[0]
    accuracy = classifier.accuracy(z, torch.as_tensor(states))
    assert accuracy["macrostate"] == 1.0
    assert classifier.predict(z[:3]).tolist() == states[:3].tolist()


def test_vae_commands(tmp_path):
    run = tmp_path / "v"
    done = subprocess.run([IMAGINE, "vae", "train", "--preset", "smoke", "--out", str(run)],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = subprocess.run([IMAGINE, "vae", "report", str(run)], capture_output=True, text=True,
                          check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "MLP probe accuracy: hand" in done.stdout and "test KL per image" in done.stdout
    assert "linear probe accuracy: macrostate" in done.stdout
    assert "active dimensions" in done.stdout and "KL per dimension" in done.stdout
    assert "right draws, 1 diagonal comp., x 0.5" in done.stdout
    assert "right draws, 5 diagonal comps." in done.stdout
    for name in ("reconstructions.png", "traversals.png", "report.json"):
        assert (run / name).is_file()
    done = subprocess.run([IMAGINE, "vae", "report", str(tmp_path / "none")], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert done.returncode == 2 and done.stderr.startswith("error:")


def test_finished_results_are_never_cut_back(tmp_path):
    smoke(tmp_path, epochs=2)
    with pytest.raises(CheckpointError, match="holds 2 finished epochs"):
        smoke(tmp_path, epochs=1)
    assert len((tmp_path / "metrics.csv").read_text().splitlines()) == 3


@pytest.fixture(scope="module")
def one_epoch_run(tmp_path_factory) -> Path:
    """A smoke V trained for one epoch, once for the tests that spoil a copy of it."""
    folder = tmp_path_factory.mktemp("one-epoch")
    smoke(folder, epochs=1)
    return folder


@pytest.mark.parametrize(
    "document, message",
    [
        ('{"format": "imagine-vae-1"}', "lacks a config mapping"),
        ("[]", "not a V checkpoint"),
        ('{"format": "other", "epoch": 1, "config": {}}', "not a V checkpoint"),
    ],
)
def test_malformed_metadata_is_reported(one_epoch_run, tmp_path, document, message):
    shutil.copytree(one_epoch_run, tmp_path, dirs_exist_ok=True)
    (tmp_path / "vae.json").write_text(document)
    with pytest.raises(CheckpointError, match=message):
        load_vae(tmp_path)
    with pytest.raises(CheckpointError, match=message):
        smoke(tmp_path, epochs=1)


def test_report_scores_fresh_images_from_the_training_pool(tmp_path):
    from imagine.envs.gesture_puzzle.dataset import save_dataset
    from imagine.models.vision_training import fresh_images_config, with_dataset

    made = DatasetConfig(n_train=100, n_test=3, seed=4, fragment_seed=5, n_cube_fragments=3)
    path = save_dataset(tmp_path / "d.safetensors", synthesize(made), made)
    config = with_dataset(vision_preset("smoke", batch_size=32), path)
    fresh = fresh_images_config(config)
    assert (fresh.fragment_seed, fresh.n_cube_fragments, fresh.seed) == (5, 3, 5)


def test_an_images_latent_does_not_depend_on_its_batch():
    """A lone image (an agent alone, or the last of a population) gets bit for bit the latent
    it gets among others: ulp differences change a training run after hundreds of episodes."""
    torch.manual_seed(0)
    vae = ConvVAE()
    images = np.random.default_rng(0).integers(0, 256, (5, 64, 64, 3), dtype=np.uint8)
    together, sigma_together = encode_images(vae, images)
    for i in range(5):
        alone, sigma_alone = encode_images(vae, images[i : i + 1])
        assert torch.equal(alone[0], together[i]) and torch.equal(sigma_alone[0], sigma_together[i])
    last, _ = encode_images(vae, images, batch_size=4)  # a last chunk of one
    assert torch.equal(last, together)
