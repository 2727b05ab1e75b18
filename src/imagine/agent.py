"""Algorithm 1: the agent that learns from real and imaginary rollouts (paper section V-B).

:func:`train` runs the loop of Algorithm 1 for one (task, method, seed) and writes a run folder:

- ``config.yaml``: the resolved :class:`~imagine.config.AgentConfig`;
- ``agent.safetensors`` + ``agent.json``: C, M, their optimizers, both memories and every random
  generator state after the last checkpointed episode; a run started again resumes there and
  continues with the same numbers as if it had never stopped;
- ``metrics.csv`` and ``tensorboard/``: returns, success, epsilon, every loss and M's accuracy.

The loop, per real time step (Algorithm 1, lines 7-19): encode, act epsilon-greedily, step,
encode, store in M_R; N_E updates of M's three networks; N_R updates of C on M_R; from episode
I_start on (method ``augmented``), I_B imagined rollouts of depth up to I_D into M_I and N_I
updates of C on M_I. The baseline is the same agent with imagination off.
"""

from __future__ import annotations

import dataclasses
import json
import math
import signal
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from imagine.checkpoint import (
    atomic_write_text,
    load_state_dict_strict,
    load_tensors,
    optimizer_from_tensors,
    optimizer_to_tensors,
    read_json,
    save_tensors,
    write_json,
)
from imagine.config import AgentConfig, from_dict
from imagine.controller import Controller, epsilon
from imagine.encoder import OracleEncoder, VaeEncoder
from imagine.env import GesturePuzzleEnv, make_composer
from imagine.env.rules import REWARD_GOAL
from imagine.errors import CheckpointError, ConfigError, Interrupted, NumericalError
from imagine.evaluate import model_accuracy
from imagine.imagination import imagine_rollouts
from imagine.memory import ReplayMemory, imaginary_fields, real_fields
from imagine.metrics import MetricsLogger
from imagine.stopping import StopSignals
from imagine.world_model import WorldModel

FORMAT = "imagine-agent-2"

NETWORK_OF = {
    "losses/mdn": "M's MDN",
    "losses/reward": "M's r-network",
    "losses/terminal": "M's d-network",
    "losses/controller_real": "C's (real batch)",
    "losses/controller_imaginary": "C's (imaginary batch)",
}


def make_encoder(config: AgentConfig):
    if config.encoder == "oracle":
        return OracleEncoder(sigma=config.oracle_sigma)
    if config.vae_run is None:
        raise ConfigError(
            "agent.encoder is vae but no V run was given (--vae RUN or encoder=oracle)"
        )
    return VaeEncoder(config.vae_run, make_composer())


class Agent:
    """C, M, the memories and the random streams of one run of Algorithm 1."""

    def __init__(self, config: AgentConfig, encoder) -> None:
        self.config = config
        self.encoder = encoder
        torch.manual_seed(config.seed)
        d = encoder.latent_dim
        self.controller = Controller(
            d, lr=config.controller_lr, gamma=config.gamma,
            target_update_period=config.target_update_period, double_dqn=config.double_dqn,
        )  # fmt: skip
        self.model = WorldModel(d, n_components=config.n_components, dropout=config.dropout,
                                lr=config.model_lr, reward_hidden=config.reward_hidden)  # fmt: skip
        self.real = ReplayMemory(config.real_memory, real_fields(d))
        self.imaginary = ReplayMemory(config.imaginary_memory, imaginary_fields(d))
        self.generator = torch.Generator().manual_seed(config.seed)
        self.env = GesturePuzzleEnv(task=config.task)
        self.env.reset(seed=config.seed)
        self.episode = 0  # episodes finished
        self.t = 0  # real time steps taken
        self.saved_window: dict[str, list[float]] = {}

    def epsilon(self) -> float:
        c = self.config
        t = self.t if c.eps_time == "step" else self.episode
        return epsilon(t, c.eps_min, c.eps_max, c.eps_decay)

    @property
    def trains_model(self) -> bool:
        return self.config.method == "augmented" or self.config.baseline_trains_m

    def controller_states(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """The states C learns from for a real batch: V's means, or draws from N(mu, sigma)."""
        if self.config.controller_input == "mu":
            return batch["mu"], batch["next_mu"]
        return tuple(
            batch[m] + batch[s] * torch.randn(batch[m].shape, generator=self.generator)
            for m, s in (("mu", "sigma"), ("next_mu", "next_sigma"))
        )

    def run_episode(self) -> dict[str, float]:
        """One episode of Algorithm 1; returns its statistics and mean losses."""
        c = self.config
        obs, info = self.env.reset()
        mu, sigma = self.encoder.encode(obs[None], np.asarray(info["macrostate"])[None])
        losses: dict[str, list[float]] = defaultdict(list)
        total, length, success, imagined = 0.0, 0, False, 0
        eps = self.epsilon()
        done = False
        while not done:
            eps = self.epsilon()
            action = self.controller.act(mu, eps, self.generator)
            obs, reward, terminated, truncated, info = self.env.step(int(action))
            next_mu, next_sigma = self.encoder.encode(
                obs[None], np.asarray(info["macrostate"])[None]
            )
            self.real.add(
                mu=mu, sigma=sigma, action=action, next_mu=next_mu, next_sigma=next_sigma,
                reward=torch.tensor([reward]), done=torch.tensor([float(terminated)]),
            )  # fmt: skip
            for _ in range(c.model_updates if self.trains_model else 0):
                batch = self.real.sample(c.model_batch, self.generator)
                for name, value in self.model.update(batch, self.generator).items():
                    losses[f"losses/{name}"].append(value)
            for _ in range(c.n_real_updates):
                b = self.real.sample(c.real_batch, self.generator)
                z, next_z = self.controller_states(b)
                losses["losses/controller_real"].append(
                    self.controller.update(z, b["action"], b["reward"], next_z, b["done"])
                )
            if c.method == "augmented" and self.episode >= c.imagination_start:
                rollouts = imagine_rollouts(
                    self.model, self.controller, mu[0], sigma[0], c.imagination_breadth,
                    c.imagination_depth, eps, self.generator,
                )  # fmt: skip
                self.imaginary.add(**rollouts)
                imagined += len(rollouts["z"])
                for _ in range(c.n_imaginary_updates):
                    b = self.imaginary.sample(c.imaginary_batch, self.generator)
                    losses["losses/controller_imaginary"].append(
                        self.controller.update(
                            b["z"], b["action"], b["reward"], b["next_z"], b["done"]
                        )
                    )
            total += reward
            length += 1
            success |= reward == REWARD_GOAL
            mu, sigma = next_mu, next_sigma
            self.t += 1
            done = terminated or truncated
        self.episode += 1
        for name, values in losses.items():
            if not math.isfinite(values[-1]):
                raise NumericalError(
                    f"{NETWORK_OF[name]} loss became {values[-1]} at real time step {self.t} "
                    f"(episode {self.episode}); the run keeps its last checkpoint"
                )
        stats = {"charts/return": total, "charts/success": float(success),
                 "charts/episode_length": float(length), "charts/epsilon": eps,
                 "charts/imagined_transitions": float(imagined)}  # fmt: skip
        stats.update({k: float(np.mean(v)) for k, v in losses.items()})
        return stats

    # --- checkpoints --------------------------------------------------------------------------

    def save(self, folder: Path, window: dict[str, list[float]] | None = None) -> None:
        """Checkpoint everything; ``window`` holds the episode statistics not yet averaged
        into a metrics row, so a run stopped between rows resumes with the same rows."""
        tensors = {f"controller.{k}": v for k, v in self.controller.state_dict().items()}
        tensors |= optimizer_to_tensors(self.controller.optimizer, "controller_optim")
        tensors |= {f"model.{k}": v for k, v in self.model.state_dict().items()}
        tensors |= optimizer_to_tensors(self.model.optimizer, "model_optim")
        tensors |= self.real.state_dict("real") | self.imaginary.state_dict("imaginary")
        tensors["rng.generator"] = self.generator.get_state()
        tensors["rng.global"] = torch.get_rng_state()
        save_tensors(folder / "agent.safetensors", tensors)
        state = self.env.np_random.bit_generator.state
        write_json(folder / "agent.json", {
            "format": FORMAT, "episode": self.episode, "t": self.t,
            "controller_updates": self.controller.updates,
            "env_rng": json.loads(json.dumps(state)), "config": dataclasses.asdict(self.config),
            "window": window or {},
        })  # fmt: skip

    def load(self, folder: Path) -> None:
        meta = read_json(folder / "agent.json", "agent checkpoint metadata")
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise CheckpointError(
                f"{folder / 'agent.json'} is not an agent checkpoint of this version"
            )
        tensors = load_tensors(folder / "agent.safetensors", "agent checkpoint")

        def part(prefix: str) -> dict[str, torch.Tensor]:
            return {
                k[len(prefix) + 1 :]: v for k, v in tensors.items() if k.startswith(prefix + ".")
            }

        where = str(folder / "agent.safetensors")
        load_state_dict_strict(self.controller, part("controller"), where)
        load_state_dict_strict(self.model, part("model"), where)
        optimizer_from_tensors(self.controller.optimizer, tensors, "controller_optim")
        optimizer_from_tensors(self.model.optimizer, tensors, "model_optim")
        self.real.load_state_dict(tensors, "real")
        self.imaginary.load_state_dict(tensors, "imaginary")
        self.generator.set_state(tensors["rng.generator"])
        torch.set_rng_state(tensors["rng.global"])
        self.env.np_random.bit_generator.state = meta["env_rng"]
        self.episode, self.t = int(meta["episode"]), int(meta["t"])
        self.saved_window = {k: [float(v) for v in vs] for k, vs in meta.get("window", {}).items()}
        self.controller.updates = int(meta["controller_updates"])


def saved_config(folder: Path) -> AgentConfig | None:
    """The config of the run in ``folder``, or None if there is none yet."""
    if not (folder / "agent.json").is_file():
        return None
    meta = read_json(folder / "agent.json", "agent checkpoint metadata")
    return from_dict(AgentConfig, meta.get("config", {}), "agent")


def check_folder(config: AgentConfig, folder: Path) -> AgentConfig | None:
    """The config of the run already in ``folder`` (None if there is none); an error if it is
    another run's (only the episode budget may differ)."""
    saved = saved_config(folder)
    if saved is not None and dataclasses.replace(saved, episodes=config.episodes) != config:
        raise CheckpointError(
            f"{folder} holds a run with another config; use a new folder or the same settings"
        )
    return saved


def train(
    config: AgentConfig,
    folder: str | Path,
    on_episode: Callable[[int], None] | None = None,
    threads: int | None = None,
    encoder: Any = None,
) -> Agent:
    """Run Algorithm 1 into ``folder``, resuming a run that was stopped there. ``encoder``:
    one made already by :func:`make_encoder` (default: made here)."""
    if threads is not None:
        torch.set_num_threads(threads)
    folder = Path(folder)
    saved = check_folder(config, folder)
    folder.mkdir(parents=True, exist_ok=True)
    agent = Agent(config, encoder if encoder is not None else make_encoder(config))
    if saved is not None:
        agent.load(folder)
    atomic_write_text(folder / "config.yaml", yaml.safe_dump(dataclasses.asdict(config)))
    logger = MetricsLogger(folder, resume_step=agent.episode)
    window: dict[str, list[float]] = defaultdict(list, agent.saved_window)
    with StopSignals() as stop:
        while agent.episode < config.episodes:
            try:
                stats = agent.run_episode()
            except NumericalError:
                logger.close()
                raise
            for key, value in stats.items():
                window[key].append(value)
            e = agent.episode
            if agent.trains_model and e % config.accuracy_every == 0:
                for key, value in model_accuracy(agent.model, agent.encoder, config.task).items():
                    logger.record(f"model/{key}_accuracy", value)
            if e % config.log_every == 0 or e == config.episodes:
                for key, values in window.items():
                    logger.record(key, float(np.mean(values)))
                logger.record("charts/time_steps", agent.t)
                logger.dump(e)
                window.clear()
            if e % config.checkpoint_every == 0 or e == config.episodes or stop.signal:
                agent.save(folder, dict(window))
            if on_episode is not None:
                on_episode(e)
            if stop.signal:
                logger.close()
                name = signal.Signals(stop.signal).name
                raise Interrupted(
                    f"{name}: stopped {folder} after episode {e} with a checkpoint; run the same "
                    "command again to resume", stop.signal,
                )  # fmt: skip
    logger.close()
    return agent


def load_agent(folder: str | Path) -> Agent:
    """The agent of a run folder, as of its last checkpoint."""
    folder = Path(folder)
    config = saved_config(folder)
    if config is None:
        raise CheckpointError(f"{folder} holds no agent run (no agent.json)")
    agent = Agent(config, make_encoder(config))
    agent.load(folder)
    return agent
