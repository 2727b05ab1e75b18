"""The classic-control environments' extras for Algorithm 1
(:class:`~imagine.learning.extras.EnvExtras`): their true dynamics as the true model of
``imagination_model: true``, and a probe of M on held-out real transitions. Their encoder is the
vector one their observation calls for."""

from __future__ import annotations

import functools

import torch

from imagine.config import AgentConfig
from imagine.envs.classic_control.true_model import (
    TRUE_MODELS,
    ClassicTrueModel,
    random_transitions,
)
from imagine.errors import ConfigError
from imagine.learning.extras import EnvExtras


def true_model(encoder, envs, config: AgentConfig) -> ClassicTrueModel:
    """The environment's own dynamics on its observations (the vector encoder's latents)."""
    if config.wrappers:
        raise ConfigError(
            f"agent.imagination_model {config.imagination_model} on {config.env} steps the bare "
            f"environment: it has no model of the wrappers {list(config.wrappers)}"
        )
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


@functools.cache
def held_out(env_id: str) -> dict[str, torch.Tensor]:
    """The probe's transitions (:func:`random_transitions`), as float32 tensors."""
    rows = random_transitions(env_id)
    return {k: torch.as_tensor(v, dtype=torch.int64 if k == "action" else torch.float32)
            for k, v in rows.items()}  # fmt: skip


@torch.no_grad()
def model_probe(model, encoder, config: AgentConfig) -> dict[str, float]:
    """M on 2000 held-out real transitions of a random policy (logged as
    ``model/<key>_accuracy``):

    - ``next_state``: the share whose most likely next state (the members' mean mode) is
      closer to the true next state than a tenth of the true step's length;
    - ``terminal`` / ``nonterminal``: d's accuracy at the true next state, over the terminal
      transitions and the others (terminal ones are rare in M's memory);
    - ``reward``: r within 0.5 of the true reward at the true next state.

    Nothing with wrappers (the transitions are the bare environment's). A random policy never
    ends Acrobot-v1 in 2000 steps, so its ``terminal`` is NaN there.
    """
    if config.wrappers:
        return {}
    device = next(model.parameters()).device
    rows = {
        k: v.to(device) for k, v in held_out(config.env.partition(":")[2] or config.env).items()
    }
    was_training = model.training
    model.eval()
    guess = model.most_likely(rows["state"], rows["action"])
    step = (rows["next"] - rows["state"]).norm(dim=-1)
    error = (guess - rows["next"]).norm(dim=-1)
    end = model.terminal.is_terminal(rows["next"])
    done = rows["done"].bool()
    reward = model.reward(rows["next"])
    model.train(was_training)
    return {"next_state": float((error < 0.1 * step).float().mean()),
            "terminal": float((end[done]).float().mean()) if done.any() else float("nan"),
            "nonterminal": float((~end[~done]).float().mean()),
            "reward": float(((reward - rows["reward"]).abs() < 0.5).float().mean())}  # fmt: skip


EXTRAS = EnvExtras(true_model=true_model, model_probe=model_probe)
