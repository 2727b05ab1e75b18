"""Typed configurations and presets.

Each part of the system has one dataclass whose fields are its hyperparameters, each documented
with the paper's symbol or the docs/design.md choice it stands for. Presets:

- ``paper``: every number of the paper (docs/design.md section 2).
- ``fast``: the default, sized so the whole study runs on a 2-core CPU; deviations documented.
- ``smoke``: seconds, for tests.

Configs read from and write to YAML (``yaml.safe_load`` only); unknown keys and bad values get a
one-line :class:`~imagine.errors.ConfigError`.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TypeVar, get_type_hints

import yaml

from imagine.errors import ConfigError

PRESETS = ("paper", "fast", "smoke")
GATES = ("none", "stop", "mask", "random")
"""The choices of ``AgentConfig.imagination_gate`` (:mod:`imagine.learning.gate`)."""
TRUST_TESTS = ("action", "step")
"""The choices of ``AgentConfig.imagination_trust_test`` (:mod:`imagine.learning.gate`)."""
TASKS: tuple[str, ...] = ("original", "hard")
"""GesturePuzzle's tasks (:mod:`imagine.envs.gesture_puzzle.rules`): one dynamics, two goals."""
IMAGINATION_MODELS = ("learned", "true", "true_mean", "true_reward", "true_end", "true_state")
"""The choices of ``AgentConfig.imagination_model``
(:mod:`imagine.envs.gesture_puzzle.true_model`)."""
REWARD_LOSSES = ("logcosh", "mse")
"""The choices of ``AgentConfig.reward_loss`` (:data:`imagine.models.world_model.REWARD_LOSSES`)."""
TERMINAL_WEIGHTS = ("none", "balanced")
"""The choices of ``AgentConfig.terminal_weight``."""
UNCERTAINTIES = ("disagreement", "support")
"""The choices of ``AgentConfig.imagination_uncertainty`` (:mod:`imagine.learning.gate`)."""
ENCODERS = ("vae", "oracle", "vector", "onehot")
"""vae: V (images); oracle: GesturePuzzle's true state; vector and onehot: an observation that
needs no V (:mod:`imagine.models.encoders`)."""


@dataclass(frozen=True)
class VisionConfig:
    """V: the beta-VAE (paper section V-B, Variational Autoencoder; docs/design.md section 2)."""

    latent_dim: int = 8
    """Size of the latent state z (the paper's 8)."""
    beta: float = 4.0
    """Weight of the KL term in the loss (paper: beta = 4)."""
    lr: float = 5e-4
    """Adam learning rate (paper: 0.0005)."""
    beta_warmup_steps: int = 0
    """Updates over which the KL weight rises linearly from 0 to beta (KL annealing, Bowman et
    al. 2016). Paper: 0, beta from the start. With few updates, beta = 4 from the start lets
    the posterior collapse for hundreds of updates before any factor is encoded."""
    batch_size: int = 2000
    """Images per update (paper: 2000)."""
    epochs: int = 1000
    """Passes over the training images (paper: 1000)."""
    n_train: int = 100_000
    """Synthesized training images (paper: 100,000)."""
    n_test: int = 10_000
    """Synthesized test images (paper: 10,000)."""
    data_seed: int = 0
    """Seed of the synthesized images."""
    seed: int = 0
    """Seed of the weights, the shuffling and the reparameterization noise."""
    n_classifier_fit: int = 20_000
    """Training images whose encoded means fit the latent classifier."""
    n_classifier_test: int = 10_000
    """Fresh images (new seed) on which the latent classifier is scored."""
    dataset: str | None = None
    """A file from `imagine dataset` to train on (e.g. made from your own fragment photos);
    None synthesizes n_train + n_test images with the procedural renderer."""
    env: str | None = None
    """Another Gymnasium environment whose frames V learns (``imagine vae train --env``): n_train
    + n_test observations of a random policy (seeded by data_seed), resized to 64 x 64 RGB;
    None: GesturePuzzle's images."""
    env_wrappers: list[str] = dataclasses.field(default_factory=list)
    """Wrappers of ``env`` (``module:Class``, in order), as the agent's ``wrappers``."""

    def __post_init__(self) -> None:
        positive = ("latent_dim", "lr", "batch_size", "epochs", "n_train", "n_test")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"vision.{name} must be positive, got {getattr(self, name)}")
        if self.beta_warmup_steps < 0:
            raise ConfigError(
                f"vision.beta_warmup_steps must be >= 0, got {self.beta_warmup_steps}"
            )
        if self.beta < 0:
            raise ConfigError(f"vision.beta must be >= 0, got {self.beta}")
        if self.batch_size > self.n_train:
            raise ConfigError(
                f"vision.batch_size ({self.batch_size}) is larger than vision.n_train "
                f"({self.n_train})"
            )
        if self.n_classifier_fit < 1 or self.n_classifier_test < 1:
            raise ConfigError("vision.n_classifier_fit and n_classifier_test must be positive")


VISION_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    # fast: a 2-core CPU in about 4 minutes. 20,000 images, 3 epochs of batch 32 (1,875
    # updates instead of the paper's 50,000), lr 1e-3 and the KL weight annealed over the first
    # 1,000 updates; the architecture, latent size and beta are the paper's.
    "fast": {
        "n_train": 20_000,
        "n_test": 2_000,
        "epochs": 3,
        "batch_size": 32,
        "lr": 1e-3,
        "beta_warmup_steps": 1_000,
        "n_classifier_fit": 10_000,
    },
    "smoke": {
        "n_train": 512,
        "n_test": 128,
        "epochs": 2,
        "batch_size": 64,
        "lr": 1e-3,
        "beta_warmup_steps": 4,
        "n_classifier_fit": 512,
        "n_classifier_test": 256,
    },
}


T = TypeVar("T")


def check_preset(preset: str) -> str:
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return preset


def vision_preset(preset: str = "fast", **overrides: Any) -> VisionConfig:
    """The V config of a preset, with ``overrides`` applied (validated)."""
    values = {**VISION_PRESETS[check_preset(preset)], **overrides}
    return from_dict(VisionConfig, values, "vision")


def from_dict(cls: type[T], values: dict[str, Any], section: str) -> T:
    """Build a config dataclass from a mapping, naming unknown keys and wrongly typed values."""
    if not isinstance(values, dict):
        raise ConfigError(f"{section} must be a mapping, got {type(values).__name__}")
    names = [f.name for f in fields(cls)]  # type: ignore[arg-type]
    hints = get_type_hints(cls)
    for key, value in values.items():
        if key not in names:
            near = difflib.get_close_matches(str(key), names, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise ConfigError(f"unknown key {section}.{key}{hint}")
        _check_type(f"{section}.{key}", value, hints[key])
    return cls(**values)


def _check_type(name: str, value: Any, hint: Any) -> None:
    text = str(hint)
    if hint is bool or text == "bool":
        ok = isinstance(value, bool)
    elif hint is int or text == "int":
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float or text == "float":
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    elif hint is str or text == "str":
        ok = isinstance(value, str)
    else:
        ok = True
    if not ok:
        raise ConfigError(
            f"{name} must be of type {getattr(hint, '__name__', text)}, got {value!r}"
        )


def to_dict(config: Any) -> dict[str, Any]:
    return dataclasses.asdict(config)


def parse_seeds(text: str) -> tuple[int, ...]:
    """Seeds as ``imagine train --seeds`` and ``imagine reproduce --seeds`` take them: a
    comma-separated list of non-negative integers and ranges ``A-B`` (both ends included),
    e.g. ``0,1,2``, ``0-4`` or ``0-2,7``; sorted, each once."""
    seeds: set[int] = set()
    try:
        for part in text.split(","):
            first, sep, last = part.strip().partition("-")
            lo = int(first)
            hi = int(last) if sep else lo
            if lo < 0 or hi < lo:
                raise ValueError
            seeds.update(range(lo, hi + 1))
    except ValueError:
        raise ConfigError(
            f"--seeds expects comma-separated integers or ranges A-B (e.g. 0,1,2 or 0-4), "
            f"got {text!r}"
        ) from None
    return tuple(sorted(seeds))


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings as a mapping, each value read as YAML (``0.5``, ``true``, ``null``),
    but as its text for a field that holds only strings (``imagination_model=true`` is the
    choice ``"true"``, not a boolean)."""
    values: dict[str, Any] = {}
    text_only = text_fields()
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ConfigError(f"--set {key.strip()}: {text!r} is not a valid value") from None
        if key.strip() in text_only and not isinstance(value, str):
            value = text.strip()
        values[key.strip()] = value
    return values


def text_fields() -> set[str]:
    """The AgentConfig fields typed ``str`` alone."""
    return {name for name, hint in get_type_hints(AgentConfig).items() if hint is str}


def load_yaml(path: str | Path) -> dict[str, Any]:
    """A YAML file that must hold a mapping (safe loader only)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        document = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        message = f"config file {path} is not valid YAML ({exc})".replace("\n", " ")
        raise ConfigError(message) from None
    if not isinstance(document, dict):
        raise ConfigError(f"config file {path} must hold a mapping, got {type(document).__name__}")
    return document


@dataclass(frozen=True)
class AgentConfig:
    """Algorithm 1: C, M and the memories (paper section V-B; docs/design.md section 2).

    Where the paper is silent the docs/design.md choice is the default and a field."""

    env: str = "imagine/GesturePuzzle-v0"
    """The environment, as ``gymnasium.make`` takes it (``module:Id`` included): the paper's
    GesturePuzzle, or any registered one with a Discrete action space (:mod:`imagine.envs`)."""
    wrappers: list[str] = dataclasses.field(default_factory=list)
    """Gymnasium wrappers (``module:Class``) applied in order to each copy of ``env``."""
    task: str = "original"
    """GesturePuzzle task: original or hard."""
    init_from: str | None = None
    """A trained run whose M starts this agent's (issue 16, reward transfer; with a folder of
    ``seed-N`` runs, the one of this agent's seed): its MDN(s), the dynamics, which `original`
    and `hard` share; r, d and C start fresh, as do the memories. Read when the run starts,
    not when it resumes. The source must use the same encoder (V run) and M's architecture."""
    hand_switch_prob: float = 0.0
    """A stochastic human (issue 16): the probability that the hand moves to another cube
    after each action (0: the paper's task; :mod:`imagine.envs.gesture_puzzle.rules`)."""
    method: str = "augmented"
    """baseline (real transitions only) or augmented (plus imaginary ones from episode I_start)."""
    episodes: int = 2000
    """Training episodes (the paper's budgets are 2000..6000)."""
    steps: int = 0
    """A budget of real time steps as well (0: none): the agent stops at whichever budget it
    reaches first; the episode running when it reaches ``steps`` ends there (truncated)."""
    seed: int = 0
    """Seed of the networks, the environment and every random draw."""
    encoder: str = "vae"
    """vae: V's latent; oracle: a fixed random embedding of the true macrostate (studies M and C
    apart from vision); vector: any other Box observation as it is (a grid flattened); onehot:
    a Discrete observation as its one-hot vector (`imagine train --env` picks these from the
    observation space)."""
    vae_run: str | None = None
    """V run folder (from `imagine vae train`) for encoder=vae."""
    oracle_sigma: float = 0.05
    """The sigma the oracle encoder reports, so latents can still be re-sampled."""
    gamma: float = 0.99
    """Discount (the paper does not say; docs/design.md: 0.99)."""
    eps_min: float = 0.001
    """epsilon_min of the exploration schedule."""
    eps_max: float = 0.8
    """epsilon_max of the exploration schedule."""
    eps_decay: float = 0.03
    """lambda of the exploration schedule."""
    eps_time: str = "step"
    """What t counts in epsilon(t): step (global time step, as written) or episode."""
    controller_input: str = "mu"
    """What C learns from for real transitions: mu (V's mean, what C acts on) or sample (a
    draw from N(mu, sigma), like the imagined states M produces). The paper does not say."""
    model_latents: str = "sample"
    """What M learns from and imagines in: sample (the paper: inputs and targets drawn from V's
    N(mu, sigma) each time a batch is built, rollouts started from a draw of the current
    posterior) or mu (V's means: M models the dynamics of the states C acts on, and rollouts
    start from the current mu). With a V whose unused dimensions have collapsed to the prior
    (sigma near 1), sample makes M learn and emit that noise."""
    model_residual: bool = False
    """M's mixture means as the current state plus a predicted change (mu_k = z + head_k, as
    PETS and MBPO predict state differences) instead of the next state itself (the paper). An
    action rotates one cube, so most of the state stays as it is: a residual M gets that for
    free and learns only the change."""
    imagination_draw: str = "sample"
    """How an imagined next state is drawn from M's mixture: sample (a component by its weight,
    then its Gaussian; the paper), mode (the mean of the heaviest component), component (a
    draw from the heaviest component's Gaussian: M's most likely next macrostate with the
    spread of its images, as a real step draws new fragments) or outcome (a component by its
    weight, then its mean: each of M's outcomes as often as M weighs it, without the
    Gaussian's spread; for a stochastic human, where the mode never moves the hand)."""
    value_expansion: int = 0
    """H: C's targets for real transitions look H steps further through M from I_start on
    (model-based value expansion, Feinberg et al. 2018; :mod:`imagine.learning.value_expansion`):
    C's greedy actions, M's most likely next states, r and d, then Q' bootstraps. 0: equation 1
    (the paper). Augmented only; beside imagination, which ``n_imaginary_updates: 0`` turns
    off."""
    value_expansion_weighting: str = "mve"
    """How the H-step target uses the horizons: mve (the H-step return alone, MVE) or steve
    (every horizon 0..H, each member of an ensemble M rolling out alone, weighted by the
    inverse of its variance over the members and the bootstrap's: STEVE, Buckman et al.
    2018; needs ``model_ensemble`` >= 2)."""
    value_expansion_members: str = "first"
    """Whose most likely next state the ``mve`` expansion follows with an ensemble M
    (``model_ensemble`` >= 2): first (member 0's) or mean (the members' mean mode,
    (1 / K) sum_k mode_k, M's point prediction in the accuracy and generalization checks).
    One member: the same either way."""
    belief: str = "observation"
    """What the trained C acts on (test episodes, ``Agent.act``): observation (V's mean mu_t of
    the current image; the paper) or filtered (augmented only, once past I_start: the belief
    b_t = w m_t + (1 - w) mu_t, b_0 = mu_0, with m_t the mean of the component of M's mixture
    for (b_{t-1}, a_{t-1}) that best explains mu_t and w ``belief_weight``: a filter of
    constant gain that averages V's reading of the image with M's prediction of it;
    :mod:`imagine.learning.belief`). C learns from V's means either way, and acts on them while
    it trains (acting on the belief in training too was measured worse: C no longer takes,
    and so never corrects, the actions its values prefer on V's means). With V, a fresh
    image's latent lies about as far from its macrostate's mean as the nearest other
    macrostate does, and M's prediction of it is near that mean
    (docs/research/v-fit-for-dynamics.md, round 11)."""
    belief_weight: float = 0.5
    """w of the ``filtered`` belief: the weight of M's prediction against V's observation, in
    [0, 1)."""
    imagination_from: str = "current"
    """Where the I_B imagined rollouts of a step start: current (the paper: each from the agent's
    current latent state, so with a near-greedy C they retrace the path C is about to take) or
    memory (Dyna, MBPO: each from the state of a transition drawn uniformly from M_R, so M
    hands C rollouts from states and actions the real path is not on)."""
    imagination_actions: str = "policy"
    """What the imagined rollouts do from their starts: policy (C acts epsilon-greedily for up
    to I_D steps; the paper) or all (one step of every action from each of the I_B starts,
    I_B x A transitions a step: M tells C what the actions its behaviour did not take would
    have done, which replay cannot; :func:`imagine.learning.imagination.every_action`)."""
    imagination_actions_until: int = 0
    """With imagination_actions all: the episode from which the agent imagines as the paper
    does instead (policy rollouts, every imagined transition kept, no gate); 0: never. Every
    action's backup fills in what C has not tried while its behaviour is young; once C's own
    choices are what matter, its policy's rollouts refine them (docs/research/model-trust.md)."""
    imagination_epsilon: float = -1.0
    """Epsilon of C's choices inside imagined rollouts; -1: the real epsilon of the moment (the
    paper's reading, near 0.001 by I_start, so rollouts follow C's greedy path)."""
    real_in_place_of_imagined: bool = False
    """The control for imagination (baseline only): from I_start on, C makes N_I more updates
    per step on real batches, exactly where and as many as the augmented agent makes on
    imagined ones, so that a gain of imagination is shown to come from M, not from one more
    update per step."""
    baseline_trains_m: bool = False
    """Train M in baseline runs too (only for its accuracy curve: C never uses it there)."""
    controller_lr: float = 1e-3
    """C's Adam learning rate."""
    target_update_period: int = 0
    """Updates between target-network copies; 0: no target network (the paper). The `fast`
    preset's augmented agent: 100 (docs/research/v-fit-for-dynamics.md, round 18)."""
    double_dqn: bool = False
    """Double DQN targets (an option; the paper uses plain DQN)."""
    real_batch: int = 64
    """Real transitions per C update."""
    imaginary_batch: int = 64
    """Imaginary transitions per C update."""
    n_real_updates: int = 1
    """N_R: C updates on real batches per time step."""
    n_imaginary_updates: int = 1
    """N_I: C updates on imaginary batches per time step."""
    real_memory: int = 50_000
    """Capacity of the real memory M_R."""
    imaginary_memory: int = 3_000
    """Capacity of the imaginary memory M_I (first in, first out)."""
    model_updates: int = 16
    """N_E: updates of each of M's networks per time step."""
    model_every: int = 1
    """Real time steps between two trainings of M (k >= 1): M's N_E updates and r and d's
    ``reward_updates`` run on the steps t with t mod k = 0 (1: every step, the paper). MBPO
    (Janner et al. 2019) trains its model every 250 environment steps; how often M needs it
    here is docs/research/speed.md."""
    reward_updates: int = 0
    """Extra updates per time step of M's r- and d-networks alone, on batches of
    ``model_batch`` (0: the paper, N_E for all three). Early, r and d know the few goal and
    illegal states seen and generalize poorly to the rest
    (docs/research/v-fit-for-dynamics.md, round 6)."""
    reward_loss: str = "logcosh"
    """The r-network's loss: logcosh (the paper) or mse. Log-cosh's gradient is at most 1
    per transition, so the rare +50 of a goal state moves r little against the many -1s; the
    squared error's grows with the error (docs/research/v-fit-for-dynamics.md, round 7)."""
    terminal_weight: str = "none"
    """How d's binary cross-entropy weighs the terminal transitions: none (the paper: as
    sampled) or balanced (each terminal one weighs as many of the others as its agent's M_R
    holds per terminal transition, so both classes weigh the same however rare the failures
    become; the positive weight of a class-weighted cross-entropy)."""
    model_batch: int = 512
    """Real transitions per M update."""
    model_lr: float = 1e-3
    """Adam learning rate of M's networks."""
    n_components: int = 5
    """Gaussians in the MDN."""
    matmul_dtype: str = "float32"
    """The dtype of C's and M's matrix products during training: float32 (the paper), or
    bfloat16 (mixed precision: weights, gradients, Adam's state, losses and the MDN's
    log-likelihood stay float32; only each layer's product rounds its operands to bfloat16, as
    a CPU with AMX or avx512_bf16 and a GPU compute it fastest; docs/benchmarks.md). Evaluation,
    planning and the checkpoints are float32 either way. An agent's numbers match its run in a
    population bitwise with float32 only."""
    model_ensemble: int = 1
    """K: members of M's MDN per agent (PETS, MBPO), each with its own initialization and its
    own bootstrap batch of M_R per update; r and d stay single. Imagination follows a member
    drawn per step and logs the members' disagreement. 1: one MDN (the paper)."""
    dropout: float = 0.5
    """Dropout in M's networks (the paper: 50% in all three)."""
    reward_dropout: float | None = None
    """Dropout in the r- and d-networks apart from the MDN's; None: ``dropout``."""
    model_hidden: int = 256
    """Units in each of the MDN's 3 hidden layers (paper: 256). A vector environment's few
    state variables need fewer (docs/suite.md: M's cost on CartPole-v1 and Acrobot-v1)."""
    reward_hidden: int = 512
    """Units in each of the r-network's 3 hidden layers (paper: 512)."""
    terminal_hidden: int = 256
    """Units in each of the d-network's 2 hidden layers (paper: 256)."""
    imagination_gate: str = "none"
    """Which imagined transitions reach M_I, by their uncertainty u (imagination_uncertainty)
    against
    tau = imagination_gate_scale * quantile_q(first-step u of the agent's recent rollouts)
    (:mod:`imagine.learning.gate`): stop (MACURA: a rollout ends at its first
    u > tau, that transition not kept), mask (M2AC: each u > tau dropped), random (the control:
    as many as mask drops, chosen at random) or none (all kept; the paper)."""
    imagination_model: str = "learned"
    """What imagination rolls out: the agent's learned M (the paper), or ``true``: the
    environment's rules observed through V (:mod:`imagine.envs.gesture_puzzle.true_model`; a
    diagnostic of what a perfect M would give with this V, as the oracle encoder is for V; never a
    result), or ``true_mean``: the same rules, the next state the mean latent of the next
    macrostate's images instead of a fresh image (a perfect M's mode: what separates it from
    ``true`` is the spread of the images); ``true_reward``: the learned M's next state with the
    rules' reward and end; ``true_end``: the learned next state and reward, the rules' end;
    ``true_state``: the rules' next state (as ``true_mean``) with the learned
    r- and d-networks. M is trained either way."""
    imagination_uncertainty: str = "disagreement"
    """The u a gate judges each imagined transition (z, a, z') by (:mod:`imagine.learning.gate`):
    disagreement (the members' mean pairwise distance between their modes of z'; needs
    model_ensemble >= 2) or support (the distance from z to the nearest start latent of a
    real transition with the same action in the agent's M_R: how far M extrapolates from its
    data; any K)."""
    imagination_gate_quantile: float = 0.95
    """q of the gate's threshold, in (0, 1]."""
    imagination_gate_scale: float = 1.0
    """Factor of the gate's threshold (> 0): tau = scale * quantile_q."""
    imagination_gate_window: int = 1000
    """Recent rollouts whose first-step disagreements set the gate's threshold."""
    imagination_adaptive: bool = False
    """Scale N_I with the agent's running acceptance a of its gate (N_I * a, rounded half up;
    a = 1 without a gate), and make no imaginary update while M is not trusted: while fewer
    than imagination_trust_floor of its one-step modes on the newest real transitions identify
    the action taken (its mode for that action is the nearest of all actions' modes to the
    observed next mu; :mod:`imagine.learning.gate`)."""
    imagination_trust_floor: float = 0.8
    """Share of right one-step predictions on the newest real transitions below which an
    adaptive agent makes no imaginary update, in [0, 1]."""
    imagination_trust_every: int = 10
    """Real time steps between two judgments of M's trust by an adaptive agent (>= 1); the
    last judgment holds in between. Judging runs every member on all actions of the newest
    100 real transitions, more than a step's imagination costs; within 10 steps at most a
    tenth of those transitions are new."""
    imagination_trust_test: str = "action"
    """How an adaptive agent judges M's one-step predictions on its newest real transitions
    (:mod:`imagine.learning.gate`): action (the member's mode for the action taken is the
    nearest of all actions' modes to the observed next mu; needs no unit, for V's latents) or
    step (the mode lies within imagination_trust_tolerance of the real step's length of the
    observed next state; for state observations, where a step's size is a scale)."""
    imagination_trust_tolerance: float = 0.1
    """With imagination_trust_test step: a prediction is right when its distance to the
    observed next state is below this share of ||next_mu - mu|| (> 0)."""
    imagination_trust_terminals: int = 0
    """With imagination_adaptive: M is trusted only while d is right as well, calling at least
    imagination_trust_floor of the newest this many real terminal transitions of M_R terminal
    (and of the newest 100 others not terminal); 0: d is not judged (the one-step test judges
    M's next state alone)."""
    imagination_fallback: bool = False
    """With imagination_adaptive: the imaginary C updates an agent does not make (M not
    trusted, N_I' below N_I, nothing in M_I yet) are made on real batches of M_R instead;
    while M is not trusted, C's real targets are not expanded through M and no rollouts are
    imagined (an agent switched by imagination_actions_until counts as trusted). An agent
    whose M is never trusted is then the replay-ratio control (the baseline with this C and
    as many updates a step), not the baseline: imagination falls back to what replay gives."""
    imagination_start: int = 1000
    """I_start: first episode with imagined rollouts."""
    imagination_breadth: int = 3
    """I_B: imagined rollouts per time step."""
    imagination_depth: int = 10
    """I_D: steps per imagined rollout at most."""
    imagination_every: int = 1
    """Real time steps between two imaginations (k >= 1): the I_B rollouts are made on the
    steps t with t mod k = 0, and C's N_I updates on M_I run every step (1: the paper; MBPO
    rolls out on a schedule too)."""
    log_every: int = 50
    """Episodes per metrics row."""
    accuracy_every: int = 250
    """Episodes between measurements of M's accuracy over all 192 x 6 transitions."""
    checkpoint_every: int = 250
    """Episodes between checkpoints (and at the end, and on SIGINT/SIGTERM)."""
    eval_episodes: int = 1000
    """Greedy test episodes of `imagine evaluate`."""

    @property
    def filter_weight(self) -> float:
        """w of the belief C acts on once it imagines (0: it acts on V's means): an augmented
        agent's ``belief_weight`` when ``belief`` is filtered (the baseline has no M), unless
        its encoder hands C the observation as it is (vector, onehot)."""
        filtered = self.belief == "filtered" and self.method == "augmented"
        exact = self.encoder in ("vector", "onehot")  # the state as it is: nothing to average
        return self.belief_weight if filtered and not exact else 0.0

    @property
    def trains_model(self) -> bool:
        """Whether M is trained: always for augmented, for the baseline only on request."""
        return self.method == "augmented" or self.baseline_trains_m

    def __post_init__(self) -> None:
        choices = {"task": TASKS, "method": ("baseline", "augmented"),
                   "encoder": ENCODERS,
                   "eps_time": ("step", "episode"),
                   "controller_input": ("mu", "sample"), "model_latents": ("sample", "mu"),
                   "imagination_draw": ("sample", "mode", "component", "outcome"),
                   "imagination_from": ("current", "memory"),
                   "imagination_actions": ("policy", "all"),
                   "imagination_gate": GATES, "imagination_model": IMAGINATION_MODELS,
                   "reward_loss": REWARD_LOSSES, "matmul_dtype": ("float32", "bfloat16"),
                   "imagination_uncertainty": UNCERTAINTIES,
                   "value_expansion_weighting": ("mve", "steve"),
                   "value_expansion_members": ("first", "mean"),
                   "belief": ("observation", "filtered")}  # fmt: skip
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(
                    f"agent.{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        positive = ("episodes", "real_batch", "imaginary_batch", "real_memory",
                    "imaginary_memory", "model_batch", "imagination_breadth",
                    "imagination_depth", "model_every", "imagination_every", "log_every",
                    "accuracy_every", "checkpoint_every",
                    "eval_episodes", "n_components", "model_ensemble", "controller_lr",
                    "model_lr", "model_hidden", "reward_hidden", "terminal_hidden",
                    "imagination_gate_scale", "imagination_gate_window")  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"agent.{name} must be positive, got {getattr(self, name)}")
        if self.value_expansion and self.method != "augmented":
            raise ConfigError("agent.value_expansion needs M: it is for method augmented")
        if not 0 <= self.value_expansion <= 3:
            raise ConfigError(f"agent.value_expansion must be 0 to 3, got {self.value_expansion}")
        if self.value_expansion_weighting == "steve" and (
            self.value_expansion < 1 or self.model_ensemble < 2
        ):
            raise ConfigError(
                "agent.value_expansion_weighting steve weighs horizons by an ensemble M's "
                f"disagreement: set agent.value_expansion >= 1 (got {self.value_expansion}) and "
                f"agent.model_ensemble >= 2 (got {self.model_ensemble})"
            )
        if not (isinstance(self.wrappers, list) and all(isinstance(w, str) for w in self.wrappers)):
            raise ConfigError(
                f"agent.wrappers must be a list of module:Class names, got {self.wrappers!r}"
            )
        for name in ("model_updates", "reward_updates", "n_real_updates", "n_imaginary_updates",
                     "target_update_period", "imagination_start", "seed", "steps",
                     "imagination_actions_until"):  # fmt: skip
            if getattr(self, name) < 0:
                raise ConfigError(f"agent.{name} must be >= 0, got {getattr(self, name)}")
        if self.imagination_actions_until and self.imagination_actions != "all":
            raise ConfigError(
                "agent.imagination_actions_until switches imagination_actions all to the "
                f"paper's policy rollouts; imagination_actions is {self.imagination_actions!r}"
            )
        if self.real_in_place_of_imagined and self.method != "baseline":
            raise ConfigError("agent.real_in_place_of_imagined is a control for method baseline")
        if not 0.0 <= self.hand_switch_prob <= 1.0:
            raise ConfigError(
                f"agent.hand_switch_prob must be in [0, 1], got {self.hand_switch_prob}"
            )
        if not 0.0 <= self.belief_weight < 1.0:
            raise ConfigError(f"agent.belief_weight must be in [0, 1), got {self.belief_weight}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ConfigError(f"agent.gamma must be in [0, 1], got {self.gamma}")
        if not (self.imagination_epsilon == -1.0 or 0.0 <= self.imagination_epsilon <= 1.0):
            raise ConfigError(
                f"agent.imagination_epsilon must be in [0, 1] or -1, got {self.imagination_epsilon}"
            )
        if not 0.0 < self.imagination_gate_quantile <= 1.0:
            raise ConfigError(
                "agent.imagination_gate_quantile must be in (0, 1], got "
                f"{self.imagination_gate_quantile}"
            )
        if (
            self.imagination_gate != "none"
            and self.imagination_uncertainty == "disagreement"
            and self.model_ensemble < 2
        ):
            raise ConfigError(
                f"agent.imagination_gate {self.imagination_gate} needs the members' disagreement:"
                f" set agent.model_ensemble >= 2 (got {self.model_ensemble}) or "
                "agent.imagination_uncertainty=support"
            )
        if not 0.0 <= self.imagination_trust_floor <= 1.0:
            raise ConfigError(
                "agent.imagination_trust_floor must be in [0, 1], got "
                f"{self.imagination_trust_floor}"
            )
        if self.imagination_trust_test not in TRUST_TESTS:
            raise ConfigError(
                f"agent.imagination_trust_test must be one of {', '.join(TRUST_TESTS)}, got "
                f"{self.imagination_trust_test!r}"
            )
        if not self.imagination_trust_tolerance > 0:
            raise ConfigError(
                "agent.imagination_trust_tolerance must be > 0, got "
                f"{self.imagination_trust_tolerance}"
            )
        if self.terminal_weight not in TERMINAL_WEIGHTS:
            raise ConfigError(
                f"agent.terminal_weight must be one of {', '.join(TERMINAL_WEIGHTS)}, got "
                f"{self.terminal_weight!r}"
            )
        if self.imagination_trust_terminals < 0:
            raise ConfigError(
                "agent.imagination_trust_terminals must be >= 0, got "
                f"{self.imagination_trust_terminals}"
            )
        if self.imagination_fallback and not self.imagination_adaptive:
            raise ConfigError(
                "agent.imagination_fallback makes the imaginary updates an adaptive agent skips "
                "on real batches: set agent.imagination_adaptive=true"
            )
        if self.imagination_trust_every < 1:
            raise ConfigError(
                f"agent.imagination_trust_every must be >= 1, got {self.imagination_trust_every}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"agent.dropout must be in [0, 1), got {self.dropout}")
        if self.reward_dropout is not None and not (
            isinstance(self.reward_dropout, int | float) and 0.0 <= self.reward_dropout < 1.0
        ):
            raise ConfigError(
                f"agent.reward_dropout must be in [0, 1) or null, got {self.reward_dropout!r}"
            )
        if not 0.0 <= self.eps_min <= self.eps_max <= 1.0:
            raise ConfigError("agent epsilons must satisfy 0 <= eps_min <= eps_max <= 1")
        if self.model_batch > self.real_memory or self.real_batch > self.real_memory:
            raise ConfigError(
                "agent.model_batch and agent.real_batch must fit in agent.real_memory"
            )
        if self.imaginary_batch > self.imaginary_memory:
            raise ConfigError("agent.imaginary_batch must fit in agent.imaginary_memory")
        if self.oracle_sigma <= 0:
            raise ConfigError("agent.oracle_sigma must be positive")


def check_imagines(config: AgentConfig, budget_option: str = "--episodes") -> AgentConfig:
    """An error if an augmented run would end before its I_start, saying which budget would
    work (``budget_option``: how the command sets it) and which I_start would. Asked of a whole
    run (`imagine train`, a study's largest budget), not of a config trained to an early
    evaluation point."""
    start, episodes = config.imagination_start, config.episodes
    if config.method == "augmented" and start >= episodes:
        raise ConfigError(
            f"agent.imagination_start ({start}) is beyond the episode budget ({episodes}): "
            f"the augmented agent would never imagine; give a budget above it "
            f"({budget_option} {2 * start} works) or start imagining earlier "
            f"(--set imagination_start={episodes // 2})"
        )
    return config


M_FAST = {"model_updates": 2, "model_batch": 128, "dropout": 0.2, "model_residual": True,
          "reward_hidden": 128, "reward_updates": 6}  # fmt: skip
"""The `fast` preset's M: N_E = 2 updates of 128 (the paper: 16 of 512) with 20% dropout, a
residual MDN, a 3 x 128 r-network and 6 more updates of r and d alone per step."""

IMAGINATION_FAST = {"imagination_draw": "mode", "imagination_start": 100,
                    "imagination_from": "memory", "n_imaginary_updates": 3}  # fmt: skip
"""The `fast` preset's imagination: M's mode, from episode 100, Dyna's starts (states of M_R),
N_I = 3 updates of C on imagined batches per step."""

VECTOR_FAST = {"dropout": 0.0, "imagination_adaptive": True, "imagination_fallback": True,
               "imagination_trust_test": "step"}  # fmt: skip
"""The `fast` augmented agent's M on state vectors (``encoder: vector``; issue 57): M, r and
d without dropout (with 20% an MDN has Acrobot's next state within a tenth of the step on
78.5% of held-out transitions, without it on 99.7%), judged every 10 steps by its one-step
error on the newest real transitions and, while wrong, replaced by replay (the fallback)."""

SMOKE = {"episodes": 300, "model_updates": 1, "model_batch": 64, "imagination_start": 100,
         "log_every": 25, "accuracy_every": 100, "checkpoint_every": 100, "eval_episodes": 200,
         "real_memory": 5000}  # fmt: skip
"""The `smoke` preset, the same for both methods: the paper's agent, small and short, to check
that everything runs (tests, `imagine reproduce --preset smoke`)."""

AGENT_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    # preset -> method -> the fields it sets over AgentConfig's defaults (the paper's settings).
    # The baseline has no M: the M and imagination fields it holds do nothing unless it trains
    # M anyway (baseline_trains_m) or is imagination's control (real_in_place_of_imagined).
    # How `fast` came to be, round by round: docs/research/fast-preset-history.md.
    "paper": {"baseline": {}, "augmented": {}},
    "fast": {
        "baseline": {**M_FAST, **IMAGINATION_FAST},
        "augmented": {
            **M_FAST,
            **IMAGINATION_FAST,
            "belief": "filtered",  # C acts on b_t = 0.5 m_t + 0.5 mu_t from I_start
            "value_expansion": 2,  # MVE: C's real targets look H = 2 steps through M
            "target_update_period": 100,  # C with a target network (the paper's has none)
            "model_ensemble": 5,  # five MDNs ...
            "imagination_gate": "mask",  # ... behind M2AC's mask on their disagreement
        },
    },
    "smoke": {"baseline": SMOKE, "augmented": SMOKE},
}
"""Presets as data, the baseline's and the augmented agent's settings side by side."""

ENCODER_PRESETS: dict[str, dict[str, dict[str, Any]]] = {"fast": {"vector": VECTOR_FAST}}
"""preset -> encoder -> what the preset's augmented agent sets over AGENT_PRESETS for that
kind of observation (GesturePuzzle's V latents keep the preset's M)."""

CONTROL_FROM_AUGMENTED = ("target_update_period",)
"""What imagination's control (a baseline with ``real_in_place_of_imagined``) takes from its
preset's augmented agent: its C, so that the two differ only in where their extra batches come
from."""


AUGMENTED_ONLY = ("value_expansion", "belief", "belief_weight")
"""Settings of the augmented agent alone (they use M): a study's baseline goes without them
(:func:`for_method`). Given to one baseline explicitly, value_expansion is an error and the
belief's fields do nothing."""


def for_method(overrides: dict[str, Any], method: str) -> dict[str, Any]:
    """A study's overrides for its agents of ``method``: a baseline's without the augmented
    agent's settings (:data:`AUGMENTED_ONLY`), so that ``--set value_expansion=2`` is the
    augmented agents' H."""
    if method == "augmented":
        return dict(overrides)
    return {k: v for k, v in overrides.items() if k not in AUGMENTED_ONLY}


def agent_preset(preset: str = "fast", **overrides: Any) -> AgentConfig:
    """The Algorithm 1 config of a preset for ``overrides``'s method (default augmented) and
    encoder (:data:`ENCODER_PRESETS`), with ``overrides`` applied (validated)."""
    by_method = AGENT_PRESETS[check_preset(preset)]
    method = overrides.get("method", AgentConfig.method)
    values = dict(by_method.get(method, {}))
    if method == "augmented":
        encoder = overrides.get("encoder", AgentConfig.encoder)
        values |= ENCODER_PRESETS.get(preset, {}).get(encoder, {})
    if method == "baseline" and overrides.get("real_in_place_of_imagined", False):
        values |= {k: by_method["augmented"][k] for k in CONTROL_FROM_AUGMENTED
                   if k in by_method["augmented"]}  # fmt: skip
    return from_dict(AgentConfig, {**values, **overrides}, "agent")
