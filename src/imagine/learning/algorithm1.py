"""Algorithm 1 of Thabet et al. (2019) for one agent, in one screen, to hold against the paper
(its line numbers in the comments). :mod:`imagine.learning.population` trains the same agent
stacked with others; ``tests/test_algorithm1.py`` checks that both give the same losses, bitwise.

Per real time step: epsilon(t), C acts epsilon-greedily on V's mean mu_t (line 8), the
environment steps (9), V encodes (10), the transition goes into M_R (11); N_E updates of M's
MDN (equation 5), r- and d-networks (12-13); N_R updates of C on M_R (equation 2) toward y_t
of equation 1, or MVE's H-step target (14-15); from episode I_start on (augmented), I_B rollouts
of up to I_D steps through M into M_I (16-18) and N_I updates of C on M_I (19-20).

No population axis: one environment, one M_R and M_I, one ``torch.Generator`` for every draw,
in the population's order. C and M are the single-agent Controller and WorldModel run through
the stacked layers of :mod:`imagine.models.stacked` with one row (K rows for an ensemble of
MDNs, each with its own Adam state): a plain ``nn.Linear`` rounds a one-unit output (r, d) and
a product of 1 to 3 rows (acting, imagining) otherwise, and one rounding apart, two runs part
within a few hundred steps. Settings the reference lacks are a :class:`ConfigError`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from imagine.config import AgentConfig
from imagine.envs.spec import make_spec
from imagine.errors import ConfigError
from imagine.learning.agent import Agent, make_encoder
from imagine.learning.gate import gate_threshold, gate_transitions
from imagine.learning.imagination import FIELDS, posterior_scale
from imagine.learning.memory import ReplayMemory, imaginary_fields, real_fields
from imagine.models import world_model as wm
from imagine.models.controller import Controller, epsilon
from imagine.models.stacked import PopulationAdam, StackedMLP, export_agent

SUPPORTED = {"imagination_model": ("learned",), "imagination_actions": ("policy",),
             "imagination_draw": ("sample", "mode"), "imagination_uncertainty": ("disagreement",),
             "imagination_adaptive": (False,), "imagination_epsilon": (-1.0,),
             "value_expansion_weighting": ("mve",), "value_expansion_members": ("first",),
             "real_in_place_of_imagined": (False,), "controller_input": ("mu",),
             "model_latents": ("sample",), "double_dqn": (False,), "matmul_dtype": ("float32",),
             "init_from": (None,)}  # fmt: skip
"""The values of the settings that the reference implements."""


def one(net: StackedMLP, x: torch.Tensor, g: torch.Generator | None = None) -> torch.Tensor:
    """A stacked network of one row on inputs (N, ...); with ``g``, dropout masks from it."""
    return net(x[None], None if g is None else [g])[0]


@dataclass
class DQN:
    """C: the Q-network, its target network Q' (None: Q' is Q) copied every ``period``
    updates, and its Adam."""

    q: StackedMLP
    target: StackedMLP | None
    optimizer: torch.optim.Optimizer
    n_actions: int
    gamma: float
    period: int
    updates: int = 0

    @torch.no_grad()
    def act(self, z: torch.Tensor, eps: float, g: torch.Generator) -> torch.Tensor:
        """Epsilon-greedy actions for states (N, D) (both draws made for every row)."""
        explore = torch.rand(len(z), generator=g) < eps
        random = torch.randint(self.n_actions, (len(z),), generator=g)
        return torch.where(explore, random, one(self.q, z).argmax(-1))

    @torch.no_grad()
    def bootstrap(self, z: torch.Tensor) -> torch.Tensor:  # max_a' Q'(z, a')
        return one(self.target if self.target is not None else self.q, z).max(-1).values

    def td_target(self, r: torch.Tensor, next_z: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        return r + self.gamma * (1.0 - d) * self.bootstrap(next_z)  # y_t (equation 1)

    def update(self, z: torch.Tensor, action: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """One Adam step on the batch's mean of (y_t - Q(s_t, a_t))^2 (equation 2)."""
        loss = (one(self.q, z).gather(-1, action[:, None]).squeeze(-1) - y).square().mean()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        if self.target is not None and self.updates % self.period == 0:
            self.target.load_state_dict(self.q.state_dict())
        return loss.detach()


@dataclass
class Model:
    """M: its K MDNs (a stack of K rows), r- and d-networks, and one Adam for all three."""

    mdn: wm.StackedMDN
    r: StackedMLP
    d: StackedMLP
    optimizer: PopulationAdam  # each member's Adam state its own, as in the population
    like: wm.MDN  # the single-agent MDN: its sizes, residual or not
    K: int

    def mixture(self, z: torch.Tensor, action: torch.Tensor, g: torch.Generator | None = None):
        """Each member's mixture for its rows (K, N, D) and actions (K, N) (a residual M's
        means: mu_k = z + head_k); with ``g``, dropout masks from it."""
        x = torch.cat([z, F.one_hot(action, self.like.n_actions).to(z)], -1)
        heads = self.mdn(x, None if g is None else [g] * self.K)
        residual = z if self.like.residual else None
        return wm.mixture_from_heads(*heads, z.shape[-1], self.like.min_sigma, residual)

    def reward(self, z: torch.Tensor, g: torch.Generator | None = None) -> torch.Tensor:
        return one(self.r, z, g).squeeze(-1)

    def terminal(self, z: torch.Tensor, g: torch.Generator | None = None) -> torch.Tensor:
        return one(self.d, z, g).squeeze(-1)  # the logit of d

    def update(self, b: dict, g: torch.Generator, c: AgentConfig, mdn: bool = True) -> dict:
        """Line 13 on a batch of M_R: member k of the MDN learns from the k-th of K bootstrap
        batches (equation 5), r (log-cosh) and d (cross-entropy) from the first, all from
        latents drawn from V's N(mu, sigma), z before z'; without ``mdn``, r and d alone."""
        K = self.K if mdn else 1
        B, losses = len(b["action"]) // K, {}
        z = b["mu"] + b["sigma"] * torch.randn(b["mu"].shape, generator=g) if mdn else None
        next_z = b["next_mu"] + b["next_sigma"] * torch.randn(b["next_mu"].shape, generator=g)
        if mdn:  # -log sum_i alpha_i N(z'; mu_i, sigma_i^2), each member on its batch
            m = self.mixture(z.view(K, B, -1), b["action"].view(K, B), g)
            losses["mdn"] = wm.mixture_nll(m, next_z.view(K, B, -1)).mean(-1)
        r, d, done = self.reward(next_z[:B], g), self.terminal(next_z[:B], g), b["done"][:B]
        losses["reward"] = wm.REWARD_LOSSES[c.reward_loss](r - b["reward"][:B]).mean()
        losses["terminal"] = F.binary_cross_entropy_with_logits(d, done, reduction="none").mean()
        self.optimizer.zero_grad()
        sum(loss.sum() for loss in losses.values()).backward()
        self.optimizer.step([0])
        return {name: loss.detach().mean() for name, loss in losses.items()}  # MDN: members' mean


@torch.no_grad()
def mve_target(C: DQN, M: Model, b: dict, c: AgentConfig) -> torch.Tensor:
    """MVE's target (:mod:`~imagine.learning.value_expansion`): H steps of C's greedy actions
    through member 0's most likely next states, r and d, then Q'."""
    z, steps = b["next_mu"], []
    for _ in range(c.value_expansion):
        action = one(C.q, z).argmax(-1).expand(M.K, -1)
        z = wm.mixture_mode(M.mixture(z.expand(M.K, *z.shape), action))[0]
        steps.append((M.reward(z), (M.terminal(z) > 0).float()))
    v = C.bootstrap(z)
    for r, d in reversed(steps):
        v = r + C.gamma * (1.0 - d) * v
    return b["reward"] + C.gamma * (1.0 - b["done"]) * v


@torch.no_grad()
def imagine(C: DQN, M: Model, start: dict, eps: float, g: torch.Generator, c: AgentConfig) -> dict:
    """Line 17: I_B rollouts of up to I_D steps from N(mu, sigma) (I_B, D): C acts
    epsilon-greedily, a member of M drawn per step gives the next state (a draw from its
    mixture, or its mode), r the reward, d the end. Ended rollouts go on in the batch, unkept,
    until all have. M_I's fields, with each transition's disagreement, rollout and step."""
    mu, sigma = start["mu"], start["sigma"]
    unit = posterior_scale(sigma)  # V's: the unit of the members' disagreement
    z = mu + sigma * torch.randn(mu.shape, generator=g)
    rows, alive, steps, kept = torch.arange(len(z)), torch.ones(len(z), dtype=torch.bool), [], []
    for t in range(c.imagination_depth):
        action = C.act(z, eps, g)
        m = M.mixture(z.expand(M.K, *z.shape), action.expand(M.K, -1))
        modes = wm.mixture_mode(m)  # (K, I_B, D)
        member = torch.randint(M.K, (len(z),), generator=g) if M.K > 1 else torch.zeros_like(rows)
        if c.imagination_draw == "mode":
            next_z = modes[member, rows]
        else:  # a component by its weight, then its Gaussian (the paper)
            next_z = wm.sample_mixture(wm.Mixture(*(f[member, rows] for f in m[:3])), g)
        done = M.terminal(next_z) > 0
        steps.append((z, action, next_z, M.reward(next_z), done.float(),
                      wm.members_spread(modes) / unit, rows, torch.full_like(rows, t)))  # fmt: skip
        kept.append(alive.clone())
        alive &= ~done
        if not alive.any():
            break
        z = next_z
    mask = torch.stack(kept)  # (T, I_B): step by step, rollouts in order within a step
    return {k: torch.stack(v)[mask] for k, v in zip(FIELDS, zip(*steps, strict=True), strict=True)}


def gated(imagined: dict, first_steps: ReplayMemory, g: torch.Generator, c: AgentConfig) -> dict:
    """What the gate keeps of the imagined transitions (:mod:`~imagine.learning.gate`): u
    against tau = scale * quantile_q of the recent rollouts' first-step u, these included."""
    u, rollout, step = (imagined.pop(key) for key in ("disagreement", "rollout", "step"))
    if c.imagination_gate == "none":
        return imagined
    first_steps.add(disagreement=u[step == 0])
    held = first_steps.data["disagreement"][0, : len(first_steps)]
    tau = gate_threshold(held, c.imagination_gate_quantile, c.imagination_gate_scale)
    keep = gate_transitions(c.imagination_gate, u, rollout, step, tau, g)
    return {key: value[keep] for key, value in imagined.items()}


def sample(memory: ReplayMemory, n: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    """n transitions drawn uniformly with replacement (from a memory of one agent)."""
    return {name: value[0] for name, value in memory.sample(n, [g]).items()}


def train(config: AgentConfig, encoder=None, record: Callable | None = None) -> Agent:
    """Algorithm 1 for ``config`` (on the CPU) to its episode or step budget, calling
    ``record(key, loss)`` after every update of M and C."""
    for name, allowed in SUPPORTED.items():
        if getattr(config, name, allowed[0]) not in allowed:
            raise ConfigError(f"agent.{name} {getattr(config, name)!r} is not in the reference "
                              f"Algorithm 1 (imagine.learning.algorithm1): it has "
                              f"{' or '.join(map(repr, allowed))}")  # fmt: skip
    c, log = config, record or (lambda key, loss: None)
    encoder, spec = make_encoder(c) if encoder is None else encoder, make_spec(c)
    D, A, K, I_B = encoder.latent_dim, spec.n_actions, c.model_ensemble, c.imagination_breadth
    torch.manual_seed(c.seed)  # line 1: C's and M's initial weights
    controller = Controller(D, A)
    model = wm.WorldModel(D, A, n_components=c.n_components, dropout=c.dropout, ensemble=K,
                          hidden=c.model_hidden, reward_hidden=c.reward_hidden,
                          terminal_hidden=c.terminal_hidden, residual=c.model_residual,
                          reward_dropout=c.reward_dropout)  # fmt: skip
    q, target = StackedMLP([controller.q]), StackedMLP([controller.q]).requires_grad_(False)
    C = DQN(q, target if c.target_update_period else None,
            torch.optim.Adam(q.parameters(), c.controller_lr, fused=True), A, c.gamma,
            c.target_update_period)  # fmt: skip
    mdn = wm.StackedMDN(model.members, model.dropout)
    r, d = (
        StackedMLP([net], model.reward_dropout) for net in (model.reward.net, model.terminal.net)
    )
    params = [*mdn.parameters(), *r.parameters(), *d.parameters()]
    n_mdn = len(list(mdn.parameters()))
    adam = PopulationAdam(params, 1, c.model_lr, [K] * n_mdn + [1] * (len(params) - n_mdn))
    M = Model(mdn, r, d, adam, model.mdn, K)
    g = torch.Generator().manual_seed(c.seed)  # every random draw of the agent
    M_R = ReplayMemory(c.real_memory, real_fields(D))  # line 2
    M_I = ReplayMemory(c.imaginary_memory, imaginary_fields(D))
    first_steps = ReplayMemory(c.imagination_gate_window, {"disagreement": ((), torch.float32)})
    envs = spec.make_vector_env(1)  # one environment (a vector env of one, as CleanRL's)
    envs.reset(seed=[c.seed])

    def encode(obs, info) -> tuple[torch.Tensor, ...]:  # lines 7 and 10: V's (mu, sigma)
        return tuple(x[0] for x in encoder.encode(*spec.encoder_input(obs, info)))

    t = episode = 0
    while episode < c.episodes and not 0 < c.steps <= t:  # line 3
        mu, sigma = encode(*envs.reset(seed=[spec.reset_seed(c.seed, episode)]))  # lines 4-5
        ended = False
        while not ended:  # line 6
            eps = epsilon(t if c.eps_time == "step" else episode, c.eps_min, c.eps_max,
                          c.eps_decay)  # fmt: skip
            a = C.act(mu[None], eps, g)  # line 8
            obs, reward, terminated, truncated, info = envs.step(a.numpy())  # line 9
            next_mu, next_sigma = encode(obs, info)  # line 10
            M_R.add(mu=mu[None], sigma=sigma[None], action=a, next_mu=next_mu[None],
                    next_sigma=next_sigma[None], reward=torch.tensor(reward, dtype=torch.float32),
                    done=torch.tensor(terminated, dtype=torch.float32))  # line 11  # fmt: skip
            training_m = c.trains_model and t % c.model_every == 0  # every k steps
            for _ in range(c.model_updates if training_m else 0):  # line 12: N_E
                for key, loss in M.update(sample(M_R, c.model_batch * K, g), g, c).items():
                    log(f"losses/{key}", loss)  # line 13
            for _ in range(c.reward_updates if training_m else 0):  # r and d alone
                for key, loss in M.update(sample(M_R, c.model_batch, g), g, c, False).items():
                    log(f"losses/{key}", loss)
            imagining = c.method == "augmented" and episode >= c.imagination_start
            for _ in range(c.n_real_updates):  # line 14: N_R
                b = sample(M_R, c.real_batch, g)
                y = (mve_target(C, M, b, c) if c.value_expansion and imagining
                     else C.td_target(b["reward"], b["next_mu"], b["done"]))  # fmt: skip
                log("losses/controller_real", C.update(b["mu"], b["action"], y))  # line 15
            if imagining and t % c.imagination_every == 0:  # line 16, every k steps
                start = (sample(M_R, I_B, g) if c.imagination_from == "memory"  # Dyna's, or mu_t
                         else {"mu": mu.expand(I_B, D), "sigma": sigma.expand(I_B, D)})  # fmt: skip
                M_I.add(**gated(imagine(C, M, start, eps, g, c), first_steps, g, c))  # 17-18
            if imagining:
                for _ in range(c.n_imaginary_updates if len(M_I) else 0):  # line 19: N_I
                    b = sample(M_I, c.imaginary_batch, g)
                    y = C.td_target(b["reward"], b["next_z"], b["done"])
                    log("losses/controller_imaginary", C.update(b["z"], b["action"], y))  # 20
            mu, sigma = next_mu, next_sigma  # line 21
            t += 1
            ended = bool(terminated[0] or truncated[0]) or 0 < c.steps <= t
        episode += 1
    for stacked, row, module in [
        (C.q, 0, controller.q),
        (r, 0, model.reward.net),
        (d, 0, model.terminal.net),
        *((mdn, k, member) for k, member in enumerate(model.members)),
    ]:
        export_agent(stacked, row, module)  # the single-agent C and M, as checkpoints hold them
    return Agent(c, encoder, controller.eval(), model.eval(), episode, t)
