"""Algorithm 1: the agent that learns from real and imaginary rollouts (paper section V-B).

:func:`imagine.learning.training.train` runs the loop of Algorithm 1 for one (task, method, seed)
and writes a run folder (:func:`imagine.learning.training.train_population` trains several seeds at
once, each into its own):

- ``config.yaml``: the resolved :class:`~imagine.config.AgentConfig`;
- ``agent.safetensors`` + ``agent.json``: C, M, their optimizers, both memories and every random
  generator state after the last checkpointed episode; a run started again resumes there and
  continues with the same numbers as if it had never stopped;
- ``metrics.csv`` and ``tensorboard/``: returns, success, epsilon, every loss and M's accuracy.

The loop, per real time step (Algorithm 1, lines 7-21; :mod:`imagine.learning.population`): encode,
act epsilon-greedily, step, encode, store in M_R; N_E updates of M's three networks; N_R updates of
C on M_R; from episode I_start on (method ``augmented``), I_B imagined rollouts of depth up to
I_D into M_I and N_I updates of C on M_I. The baseline is the same agent with imagination off.

:class:`Agent` is a trained agent as evaluation, planning and the generalization test use it:
its config, encoder, C and M. ``Agent.load(RUN)`` reads one; ``agent.act(observations)`` gives
C's greedy (or epsilon-greedy) actions for camera images, what a robot calls at each step;
``agent.save(FOLDER)`` writes it (config, C, M and V, no memories) where ``Agent.load`` and
``imagine evaluate`` read it::

    agent = Agent.load("runs/hard-aug/seed-0")
    actions = agent.act(images)  # uint8 (N, 64, 64, 3) -> int64 (N,)
    agent.save("robot/agent")
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from imagine import ENV_ID
from imagine.checkpoint import changed_fields, load_state_dict_strict, read_json, save_tensors
from imagine.config import AgentConfig, from_dict
from imagine.envs.spec import make_spec
from imagine.errors import CheckpointError, ConfigError, ObservationError
from imagine.learning.agent_checkpoint import READABLE_FORMATS, part, read_checkpoint, save_agent
from imagine.learning.belief import BeliefTracker
from imagine.learning.extras import extras_of
from imagine.learning.population import new_networks
from imagine.models.controller import Controller
from imagine.models.encoders import ImageEncoder, OneHotEncoder, VectorEncoder
from imagine.models.world_model import WorldModel


def make_encoder(config: AgentConfig, device: str | torch.device = "cpu"):
    """What C and M see: the environment's own encoder where it has one (GesturePuzzle: V or
    the oracle, :mod:`imagine.learning.extras`), else the one its observation space calls for."""
    own = extras_of(config.env).make_encoder
    return own(config, device) if own is not None else generic_encoder(config, device)


ENCODER_OF_KIND = {"vector": "vector", "discrete": "onehot", "image": "vae"}
"""The encoder each kind of observation (:func:`imagine.envs.gym.observation_kind`) needs."""

UNBOUNDED_EPISODES = 1_000_000_000
"""The episode budget of a run given only a step budget (``--steps``)."""


def with_encoder_of_env(values: dict[str, Any]) -> dict[str, Any]:
    """For an environment other than GesturePuzzle with no encoder chosen: the one its
    observation space calls for (:data:`ENCODER_OF_KIND`)."""
    from imagine.envs.spec import gym_spec

    env = values.get("env", ENV_ID)
    if env == ENV_ID or "encoder" in values:
        return values
    kind = gym_spec(env, tuple(values.get("wrappers", []))).kind
    return {**values, "encoder": ENCODER_OF_KIND[kind]}


def generic_encoder(config: AgentConfig, device: str | torch.device = "cpu"):
    """The encoder of a Gymnasium environment's observations (:mod:`imagine.models.encoders`)."""
    spec = make_spec(config)
    needed = ENCODER_OF_KIND[spec.kind]
    if config.encoder != needed:
        raise ConfigError(
            f"{config.env} has {spec.kind} observations: set agent.encoder={needed} "
            f"(got {config.encoder})"
        )
    if needed == "vae":
        return image_encoder(config, device)
    space = spec.observation_space
    return VectorEncoder(space.shape) if needed == "vector" else OneHotEncoder(space.n)


def image_encoder(config: AgentConfig, device: str | torch.device = "cpu") -> ImageEncoder:
    """V of ``config.vae_run``, which must have learned ``config.env``'s frames."""
    if config.vae_run is None:
        raise ConfigError(
            f"{config.env} has image observations: train V on its frames first "
            f"(imagine vae train --env {config.env} --out RUN) and pass --vae RUN"
        )
    encoder = ImageEncoder(config.vae_run, device)
    learned = (encoder.vision_config.env, list(encoder.vision_config.env_wrappers))
    if learned != (config.env, list(config.wrappers)):
        raise ConfigError(
            f"V run {config.vae_run} learned the frames of {learned[0] or 'GesturePuzzle'} "
            f"(wrappers {learned[1]}), not of {config.env} (wrappers {list(config.wrappers)})"
        )
    return encoder


SAVED_VAE = "vae"
"""The folder, inside a saved agent's (:meth:`Agent.save`), of the V it sees through."""


@dataclasses.dataclass(repr=False)
class Agent:
    """A trained agent: C and M (single-agent modules, eval mode) after ``episode`` episodes
    and ``t`` real time steps."""

    config: AgentConfig
    encoder: Any
    controller: Controller
    model: WorldModel
    episode: int
    t: int
    memory_starts: tuple[torch.Tensor, torch.Tensor] | None = None
    """The start latents mu_t and actions a_t of the real transitions in its M_R (what the
    ``support`` uncertainty measures against, :mod:`imagine.learning.gate`); None if not saved."""
    _belief: BeliefTracker | None = dataclasses.field(default=None, repr=False, compare=False)

    def __repr__(self) -> str:
        """One short line: environment (and task), method, encoder, episodes and steps; never
        the networks or the memory."""
        c = self.config
        env = f"{c.env}, task={c.task}" if c.env == ENV_ID else c.env
        return (f"Agent(env={env}, method={c.method}, encoder={c.encoder}, "
                f"episodes={self.episode}, steps={self.t})")  # fmt: skip

    @classmethod
    def load(cls, folder: str | Path) -> Agent:
        """The agent of a run folder, as of its last checkpoint (:func:`load_agent`)."""
        return load_agent(folder)

    def act(
        self,
        observations: np.ndarray,
        macrostates: np.ndarray | None = None,
        epsilon: float = 0.0,
        rng: np.random.Generator | None = None,
        episode_start: bool | np.ndarray = True,
    ) -> np.ndarray:
        """C's actions for observations: uint8 images (N, 64, 64, 3), or one (64, 64, 3) for
        one action (another environment's: a batch of its observations, or one). Greedy
        (argmax_a Q(mu, a) with mu from the encoder), or with ``epsilon`` a uniform random
        action that often, drawn from ``rng``. ``macrostates`` (N, 4) only for the oracle
        encoder, which reads the true state instead of the image.

        An agent that acts on a filtered belief (``belief: filtered``, :mod:`imagine.learning.
        belief`) keeps one per row between calls: ``episode_start`` (one bool, or one per row)
        says which observations start an episode; False continues the episode of the same
        row of the previous call (the same N). True everywhere (the default) acts on V's means,
        as the first step of an episode does."""
        images = np.asarray(observations)
        one = check_observations(self.encoder, images)
        if one:
            images = images[None]
            macrostates = None if macrostates is None else np.asarray(macrostates)[None]
        if self.config.encoder == "oracle" and macrostates is None:
            raise ConfigError("an oracle-encoder agent acts on macrostates: pass macrostates")
        if macrostates is not None and np.shape(macrostates) != (len(images), 4):
            given = np.shape(macrostates[0]) if one else np.shape(macrostates)
            raise ObservationError(
                f"macrostates are (4,) for one observation or (N, 4) for N; got {given} "
                f"beside {'one observation' if one else f'{len(images)} observations'}"
            )
        belief, rows = self._episodes(len(images), episode_start), np.arange(len(images))
        actions = greedy_actions(self.controller, self.encoder, images, macrostates, belief, rows)
        if epsilon > 0:
            rng = rng if rng is not None else np.random.default_rng()
            explore = rng.random(len(actions)) < epsilon
            actions = np.where(explore, rng.integers(self.controller.n_actions, size=len(actions)),
                               actions)  # fmt: skip
        if belief is not None and epsilon > 0:  # M predicts from the action taken
            belief.acted(torch.as_tensor(actions), torch.as_tensor(rows))
        return actions[0] if one else actions

    def _episodes(self, n: int, episode_start: bool | np.ndarray) -> BeliefTracker | None:
        """The belief tracker of :meth:`act`'s ``n`` rows (None if this agent acts on mu), with
        the rows that start an episode restarted."""
        if self.config.filter_weight <= 0 or self.episode < self.config.imagination_start:
            return None
        start = np.broadcast_to(np.asarray(episode_start, dtype=bool), (n,))
        if self._belief is None or len(self._belief.started) != n:
            if not start.all():
                raise ConfigError(
                    "episode_start=False continues an episode of the previous call: give it "
                    "as many observations as that call, after a call that started them"
                )
            self._belief = belief_tracker(self, n)
        self._belief.restart(torch.as_tensor(np.flatnonzero(start)))
        return self._belief

    def save(self, folder: str | Path) -> Path:
        """Write this agent (its config, C, M, the start states of its M_R where it has
        them, and V where it sees through one) into ``folder``, for :meth:`load` and
        ``imagine evaluate``; not a run that training resumes (no memories, optimizers or
        random streams). V goes into ``folder/vae`` (weights as safetensors, config as JSON,
        and its latent classifier where it has one), so the folder loads wherever V's own
        run has gone. Returns the folder."""
        tensors = {f"controller.{k}": v for k, v in self.controller.state_dict().items()}
        tensors |= {f"model.{k}": v for k, v in self.model.state_dict().items()}
        if self.memory_starts is not None:
            tensors["real.mu"], tensors["real.action"] = self.memory_starts
        values = {"episode": self.episode, "t": self.t, "config": dataclasses.asdict(self.config)}
        vision = getattr(self.encoder, "vae", None)
        if vision is not None:
            values["vae"] = SAVED_VAE
        folder = save_agent(Path(folder), tensors, values)
        if vision is not None:
            from imagine.models.vision_training import save_vae

            save_vae(folder / SAVED_VAE, vision, self.encoder.vision_config, self.encoder.epoch, {})
            classifier = getattr(self.encoder, "classifier", None)
            if classifier is not None:
                save_tensors(folder / SAVED_VAE / "classifier.safetensors",
                             classifier.state_dict())  # fmt: skip
        return folder


def check_observations(encoder, observations: np.ndarray) -> bool:
    """Whether ``observations`` are one observation (True) or a batch of them (False), as the
    encoder's ``observation_shape`` and ``observation_dtype`` call for; an
    :class:`ObservationError` naming the expected and the given shape otherwise. An encoder
    without an ``observation_shape`` (the oracle, which reads macrostates) takes any."""
    x = observations
    shape = getattr(encoder, "observation_shape", None)
    if shape is None:
        return x.ndim == getattr(encoder, "observation_ndim", 3)

    def fits(given: tuple[int, ...]) -> bool:
        return len(given) == len(shape) and all(
            isinstance(e, str) or e == g for e, g in zip(shape, given, strict=True)
        )

    dtype = getattr(encoder, "observation_dtype", None)
    kind_ok = (
        dtype is None
        or (dtype == "integer" and x.dtype.kind in "iu")
        or (dtype != "integer" and x.dtype == dtype)
    )
    if isinstance(encoder, ImageEncoder) and x.ndim >= 1 and x.shape[-1] not in (1, 3, 4):
        kind_ok = False  # channels: gray, RGB or RGBA
    one = x.ndim == len(shape) and fits(x.shape)
    batch = x.ndim == len(shape) + 1 and fits(x.shape[1:])
    if kind_ok and (one or batch):
        return one
    what = {"uint8": "uint8 images", "integer": "integer observations"}.get(dtype, "observations")
    one_shape = "(" + ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"
    batch_shape = "(" + ", ".join(["N", *map(str, shape)]) + ")"
    raise ObservationError(
        f"this agent acts on {what} of shape {one_shape} (one) or {batch_shape} (a batch); "
        f"got {x.dtype} of shape {tuple(x.shape)}"
    )


@torch.no_grad()
def greedy_actions(
    controller: Controller,
    encoder,
    images: np.ndarray,
    states: np.ndarray | None,
    belief: BeliefTracker | None = None,
    rows: np.ndarray | None = None,
) -> np.ndarray:
    """argmax_a Q(mu, a) for a batch of observations (images (N, 64, 64, 3) for GesturePuzzle),
    mu from the encoder: int64 (N,). With a ``belief`` tracker, Q of the belief of each of
    ``rows`` (its episodes) instead of mu, and the actions recorded in it."""
    mu, _ = encoder.encode(images, states)
    if belief is not None:
        mu = belief.observe(mu, torch.as_tensor(rows))
    device = next(controller.parameters()).device
    was_training = controller.training
    controller.eval()
    actions = controller(mu.to(device)).argmax(-1).cpu().numpy()
    controller.train(was_training)
    if belief is not None:
        belief.acted(torch.as_tensor(actions), torch.as_tensor(rows))
    return actions


def belief_tracker(agent: Agent, n: int) -> BeliefTracker | None:
    """The belief of ``n`` episodes of ``agent`` side by side, if it acts on one (an augmented
    agent with ``belief: filtered`` past its I_start); None if it acts on V's means."""
    c = agent.config
    if c.filter_weight <= 0 or agent.episode < c.imagination_start:
        return None
    return BeliefTracker(agent.model, c.filter_weight, n, agent.encoder.latent_dim)


def saved_config(folder: Path) -> AgentConfig | None:
    """The config of the run in ``folder``, or None if there is none yet."""
    if not (folder / "agent.json").is_file():
        return None
    meta = read_json(folder / "agent.json", "agent checkpoint metadata")
    return from_dict(AgentConfig, meta.get("config", {}), "agent")


def check_folder(config: AgentConfig, folder: Path) -> AgentConfig | None:
    """The config of the run already in ``folder`` (None if there is none); an error if it is
    another run's (only the budgets, episodes and steps, may differ)."""
    saved = saved_config(folder)
    budget = {"episodes": config.episodes, "steps": config.steps}
    if saved is not None and dataclasses.replace(saved, **budget) != config:
        differ = changed_fields(vars(saved), vars(config), skip=budget)
        raise CheckpointError(
            f"{folder} holds a run with another config ({differ}); use a new folder or the "
            "same settings"
        )
    return saved


def load_agent(folder: str | Path) -> Agent:
    """The agent of a run folder, as of its last checkpoint."""
    folder = Path(folder)
    config = saved_config(folder)
    if config is None:
        raise CheckpointError(f"{folder} holds no agent run (no agent.json)")
    tensors, meta = read_checkpoint(folder, READABLE_FORMATS)
    if meta.get("vae") == SAVED_VAE:  # a saved agent carries its V
        config = dataclasses.replace(config, vae_run=str(folder / SAVED_VAE))
    encoder = make_encoder(config)
    n_actions = make_spec(config).n_actions
    controller, model = new_networks(config, encoder.latent_dim, n_actions)
    where = str(folder / "agent.safetensors")
    load_state_dict_strict(controller, part(tensors, "controller"), where)
    load_state_dict_strict(model, part(tensors, "model"), where)
    starts = None
    if "real.mu" in tensors and "real.action" in tensors:
        starts = (tensors["real.mu"], tensors["real.action"])
    return Agent(config, encoder, controller.eval(), model.eval(), int(meta["episode"]),
                 int(meta["t"]), starts)  # fmt: skip
