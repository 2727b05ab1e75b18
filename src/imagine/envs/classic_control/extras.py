"""The classic-control environments' extras for Algorithm 1
(:class:`~imagine.learning.extras.EnvExtras`): their true dynamics as the true model of
``imagination_model: true``. Their encoder is the vector one their observation calls for."""

from __future__ import annotations

from imagine.config import AgentConfig
from imagine.envs.classic_control.true_model import TRUE_MODELS, ClassicTrueModel
from imagine.errors import ConfigError
from imagine.learning.extras import EnvExtras


def true_model(encoder, envs, config: AgentConfig) -> ClassicTrueModel:
    """The environment's own dynamics on its observations (the vector encoder's latents)."""
    if config.encoder != "vector":
        raise ConfigError(
            f"agent.imagination_model {config.imagination_model} on {config.env} steps the "
            f"environment from its observations: use encoder=vector (got {config.encoder})"
        )
    if config.imagination_model != "true":
        raise ConfigError(
            f"{config.env} has one true model, its own dynamics: agent.imagination_model is "
            f"learned or true (got {config.imagination_model})"
        )
    return TRUE_MODELS[config.env.partition(":")[2] or config.env]()


EXTRAS = EnvExtras(true_model=true_model)
