"""What an environment adds to Algorithm 1 beyond its spec (:mod:`imagine.envs.spec`): its own
encoder, a probe of M logged with the metrics, and its true dynamics for imagination's
diagnostics (``imagination_model``). Any environment goes without (the encoder then follows its
observation space, :mod:`imagine.models.encoders`).

An environment's extras are named by an entry-point string (``"module:attribute"``, as
Gymnasium names environments) in :data:`imagine.EXTRAS`, so the core imports no environment:
GesturePuzzle's are :data:`imagine.envs.gesture_puzzle.extras.EXTRAS`, and a user's own
environment adds its own with :func:`register_extras`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import imagine
from imagine.errors import ConfigError


@dataclass(frozen=True)
class EnvExtras:
    make_encoder: Callable[..., Any] | None = None
    """(config, device) -> the encoder of C and M's inputs, in place of the one the
    observation space calls for."""
    model_probe: Callable[..., dict[str, float]] | None = None
    """(M, encoder, config) -> accuracies, logged as ``model/<key>_accuracy`` every
    ``accuracy_every`` episodes."""
    true_model: Callable[..., Any] | None = None
    """(encoder, vector env, config) -> the environment's own dynamics in the encoder's latent
    space, a model imagination can roll out instead of M (a diagnostic, never a result)."""


NO_EXTRAS = EnvExtras()


def register_extras(env_id: str, entry_point: str) -> None:
    """Name ``env_id``'s extras: ``"module:attribute"``, an :class:`EnvExtras`."""
    imagine.EXTRAS[env_id] = entry_point


def extras_of(env_id: str) -> EnvExtras:
    """The extras of an environment (:data:`NO_EXTRAS` if it has none). For ``module:Id``
    the module is imported first, as ``gymnasium.make`` does, so extras it registers on import
    are found, under ``module:Id`` or ``Id``."""
    module, colon, bare = env_id.partition(":")
    if colon:
        try:
            importlib.import_module(module)
        except ImportError as e:
            raise ConfigError(f"cannot import {module} (of environment {env_id}): {e}") from None
    entry_point = imagine.EXTRAS.get(env_id) or (imagine.EXTRAS.get(bare) if colon else None)
    if entry_point is None:
        return NO_EXTRAS
    module, _, name = entry_point.partition(":")
    extras = getattr(importlib.import_module(module), name, None)
    if not isinstance(extras, EnvExtras):
        raise ConfigError(f"{entry_point} (the extras of {env_id}) is not an EnvExtras")
    return extras
