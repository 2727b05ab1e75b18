"""GesturePuzzle's extras for Algorithm 1 (:class:`~imagine.learning.extras.EnvExtras`): V or the
oracle as its encoder, M's accuracy over all 192 x 6 transitions as its probe, and its rules
observed through V as the true model of ``imagination_model``."""

from __future__ import annotations

import torch

from imagine.config import AgentConfig
from imagine.envs.gesture_puzzle import make_composer
from imagine.envs.gesture_puzzle.encoders import OracleEncoder, VaeEncoder
from imagine.envs.gesture_puzzle.evaluation import model_accuracy
from imagine.envs.gesture_puzzle.true_model import TrueLatentModel
from imagine.errors import ConfigError
from imagine.learning.extras import EnvExtras


def make_encoder(config: AgentConfig, device: str | torch.device = "cpu"):
    """``config.encoder``: V or the oracle."""
    if config.encoder not in ("vae", "oracle"):
        raise ConfigError(
            f"agent.encoder {config.encoder} is not for {config.env}: use vae or oracle"
        )
    if config.encoder == "oracle":
        return OracleEncoder(sigma=config.oracle_sigma)
    if config.vae_run is None:
        raise ConfigError(
            "agent.encoder is vae but no V run was given (--vae RUN or encoder=oracle)"
        )
    return VaeEncoder(config.vae_run, make_composer(), device=device)


def model_probe(model, encoder, config: AgentConfig) -> dict[str, float]:
    """M's accuracy over the task's 192 x 6 transitions (:func:`model_accuracy`)."""
    return model_accuracy(model, encoder, config.task, config.hand_switch_prob)


def true_model(encoder, envs, config: AgentConfig) -> TrueLatentModel:
    """The rules of ``config.task`` through the encoder, drawing images as ``envs`` does."""
    return TrueLatentModel(encoder, envs.composer, config.task, config.seed,
                           fresh=config.imagination_model == "true")  # fmt: skip


EXTRAS = EnvExtras(make_encoder=make_encoder, model_probe=model_probe, true_model=true_model)
