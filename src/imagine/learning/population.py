"""Algorithm 1 for a population: the seeds of one (task, method) trained in lockstep.

Every real time step, each running agent takes one step in its own environment (one vectorized
environment for all), V encodes every agent's observation in one batch, and each of the updates
of Algorithm 1 (lines 12-20) is one batched computation over the agents' stacked networks
(:mod:`imagine.models.stacked`): N_E updates of M, N_R updates of C on real batches, I_B imagined
rollouts of depth up to I_D into M_I and N_I updates of C on imaginary batches.

Each agent keeps what makes it an independent run: its environment and episodes, its memories
M_R and M_I, its epsilon, its Adam state and its own ``torch.Generator`` for every random draw
(batches, latent re-sampling, dropout masks, exploration, mixture samples). Agent i draws the
same numbers in the same order whatever the other agents do, so a population of one is training
alone, and an agent's numbers in a population equal its numbers alone
(``tests/test_population.py``: bitwise on a CPU with one thread and the oracle encoder; V
encodes every agent's observation in one batch, which can round a latent differently from a
batch of one). Agents run until their own episode budget; one whose loss
becomes non-finite is stopped and reported while the others go on.

Checkpoints are per agent, one run folder each, in the single-agent format (the state dicts of
:class:`~imagine.models.controller.Controller` and
:class:`~imagine.models.world_model.WorldModel`): a run trained in a population can be resumed,
evaluated or planned with alone, and the other way round.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from imagine.checkpoint import (
    load_state_dict_strict,
)
from imagine.config import AgentConfig
from imagine.envs.spec import EnvSpec, make_spec
from imagine.errors import CheckpointError, ConfigError
from imagine.learning.extras import extras_of
from imagine.learning.gate import (
    TRUST_RECENT,
    ModelTrust,
    imaginary_updates,
    one_step_close,
    one_step_right,
    support_distance,
    terminal_right,
)
from imagine.learning.imagination import (
    SplitModel,
    actions_at,
    imagine_rollouts,
    posterior_scale,
)
from imagine.learning.memory import ReplayMemory, imaginary_fields, real_fields
from imagine.learning.value_expansion import expanded_target, steve_target
from imagine.models.controller import Controller, PopulationController, epsilon
from imagine.models.stacked import agent_normal, export_agent, import_agent, set_matmul_dtype
from imagine.models.world_model import PopulationWorldModel, WorldModel

NETWORK_OF = {
    "losses/mdn": "M's MDN",
    "losses/reward": "M's r-network",
    "losses/terminal": "M's d-network",
    "losses/controller_real": "C's (real batch)",
    "losses/controller_imaginary": "C's (imaginary batch)",
}


def new_networks(
    config: AgentConfig, latent_dim: int, n_actions: int
) -> tuple[Controller, WorldModel]:
    """One agent's freshly initialized C and M (seeded with its seed)."""
    torch.manual_seed(config.seed)
    controller = Controller(latent_dim, n_actions)
    model = WorldModel(latent_dim, n_actions, n_components=config.n_components,
                       dropout=config.dropout,
                       hidden=config.model_hidden, reward_hidden=config.reward_hidden,
                       terminal_hidden=config.terminal_hidden,
                       residual=config.model_residual,
                       reward_dropout=config.reward_dropout,
                       ensemble=config.model_ensemble)  # fmt: skip
    return controller, model


def check_population(configs: Sequence[AgentConfig]) -> None:
    """A population shares every setting but the seed."""
    if not configs:
        raise ConfigError("a population needs at least one agent")
    shared = dataclasses.replace(configs[0], seed=0)
    for config in configs[1:]:
        if dataclasses.replace(config, seed=0) != shared:
            raise ConfigError("the agents of a population may differ only in their seed")


class Population:
    """C, M, memories, environments and random streams of P runs of Algorithm 1."""

    def __init__(
        self,
        configs: Sequence[AgentConfig],
        encoder,
        device: str | torch.device = "cpu",
        spec: EnvSpec | None = None,
    ) -> None:
        check_population(configs)
        self.configs = list(configs)
        self.config = c = configs[0]
        self.encoder = encoder
        self.spec = spec if spec is not None else make_spec(c)
        self.extras = extras_of(c.env)  # its encoder, probe of M, true model, if any
        self.n_actions = self.spec.n_actions
        self.device = torch.device(device)
        self.size = P = len(configs)
        d = encoder.latent_dim
        networks = [new_networks(config, d, self.n_actions) for config in configs]
        self.controller = PopulationController(
            [n[0].to(self.device) for n in networks], lr=c.controller_lr, gamma=c.gamma,
            target_update_period=c.target_update_period, double_dqn=c.double_dqn,
        )  # fmt: skip
        self.model = PopulationWorldModel(
            [n[1].to(self.device) for n in networks], c.model_lr, c.reward_loss
        )
        set_matmul_dtype(self.controller, c.matmul_dtype)
        set_matmul_dtype(self.model, c.matmul_dtype)
        self.templates = copy.deepcopy(networks[0])  # single-agent modules for export
        self.real = ReplayMemory(c.real_memory, real_fields(d), P, self.device)
        self.imaginary = ReplayMemory(c.imaginary_memory, imaginary_fields(d), P, self.device)
        self.trust = ModelTrust(c, P, self.device)
        self.generators = [torch.Generator(self.device).manual_seed(x.seed) for x in configs]
        self.envs = self.spec.make_vector_env(P)
        self.imagined_by = self.model  # what imagination rolls out (imagination_model)
        if c.imagination_model != "learned":
            true_model = self.extras.true_model
            if true_model is None:
                raise ConfigError(
                    f"agent.imagination_model {c.imagination_model} imagines with the "
                    f"environment's own dynamics; {self.spec.env_id} has none"
                )
            rules = true_model(encoder, self.envs, c)
            self.imagined_by = {"true_reward": SplitModel(self.model, rules),
                                "true_end": SplitModel(self.model, self.model, rules),
                                "true_state": SplitModel(rules, self.model)}.get(
                                    c.imagination_model, rules)  # fmt: skip
        self.envs.reset(seed=[x.seed for x in configs])
        self._env_done = np.zeros(P, dtype=bool)  # an env to reset before it steps again
        self.episode = [0] * P  # episodes finished
        self.t = [0] * P  # real time steps taken
        self.active = [True] * P
        self.failures: dict[int, str] = {}
        self._starting = [True] * P  # the next step starts a new episode
        self.mu = torch.zeros(P, d, device=self.device)
        self.sigma = torch.zeros(P, d, device=self.device)
        self._episode = [EpisodeTotals() for _ in range(P)]
        self._loss_sum: dict[str, torch.Tensor] = {}
        self._loss_count: dict[str, torch.Tensor] = {}

    def epsilon(self, agent: int) -> float:
        c = self.config
        t = self.t[agent] if c.eps_time == "step" else self.episode[agent]
        return epsilon(t, c.eps_min, c.eps_max, c.eps_decay)

    def finished(self, agent: int) -> bool:
        """Whether an agent has reached its budget (episodes, or real time steps)."""
        c = self.configs[agent]
        return self.episode[agent] >= c.episodes or 0 < c.steps <= self.t[agent]

    def stop(self, agent: int) -> None:
        """Take an agent out of the lockstep (budget reached, stopped or failed)."""
        self.active[agent] = False

    # --- one real time step of every running agent (Algorithm 1, lines 7-21) ------------------

    def step(self) -> list[tuple[int, dict[str, float]]]:
        """One real time step of every running agent; returns (agent, statistics) of each
        episode that ended in it."""
        c = self.config
        self._start_episodes()
        live = [i for i in range(self.size) if self.active[i]]
        if not live:
            return []
        rows = torch.as_tensor(live, device=self.device)
        gens = [g if self.active[i] else None for i, g in enumerate(self.generators)]
        eps = [self.epsilon(i) for i in range(self.size)]
        action = self.controller.act(self.mu.unsqueeze(1), eps, gens)[:, 0]  # C acts on mu_t
        obs, reward, terminated, truncated, info = self.envs.step(action.cpu().numpy())
        self._env_done |= terminated | truncated
        won = self.spec.success(reward, info)
        next_mu, next_sigma = self._encode(live, *self.spec.encoder_input(obs, info))
        self.real.add_each(
            live, mu=self.mu[rows], sigma=self.sigma[rows], action=action[rows],
            next_mu=next_mu, next_sigma=next_sigma,
            reward=torch.as_tensor(reward[live], dtype=torch.float32),
            done=torch.as_tensor(terminated[live], dtype=torch.float32),
        )  # fmt: skip
        self._train_model(live, gens)
        self._learn_from_real(live, c.n_real_updates, "losses/controller_real")
        if c.real_in_place_of_imagined:  # the control for imagination, from I_start on
            past = [i for i in live if self.episode[i] >= c.imagination_start]
            self._learn_from_real(past, c.n_imaginary_updates, "losses/controller_real_extra")
        self._imagine(live, eps)
        self.mu[rows], self.sigma[rows] = next_mu, next_sigma
        ended = []
        for i in live:
            totals = self._episode[i]
            totals.add(float(reward[i]), eps[i], None if won is None else bool(won[i]))
            self.t[i] += 1
            out_of_steps = 0 < self.configs[i].steps <= self.t[i]  # truncated by the budget
            if terminated[i] or truncated[i] or out_of_steps:
                self.episode[i] += 1
                self._starting[i] = True
                stats = self._end_episode(i)
                if stats is not None:
                    ended.append((i, stats))
        return ended

    def _train_model(self, live: list[int], gens: list[torch.Generator | None]) -> None:
        """Lines 12-13 for the agents whose step is one of M's (``model_every``): N_E updates
        of M (MDN, r and d), then ``reward_updates`` of r and d alone."""
        c = self.config
        due = [i for i in live if self.t[i] % c.model_every == 0] if c.trains_model else []
        if not due:
            return
        if len(due) < len(live):
            gens = [g if i in due else None for i, g in enumerate(gens)]
        rows = torch.as_tensor(due, device=self.device)
        weight = self._terminal_weight()
        resample = c.model_latents == "sample"
        for _ in range(c.model_updates):
            # K bootstrap batches, one per member of the MDN (PETS); one batch for K = 1
            batch = self.real.sample(c.model_batch * c.model_ensemble, gens)
            losses = self.model.update(batch, gens, resample=resample, terminal_weight=weight)
            for name, loss in losses.items():
                self._record(f"losses/{name}", loss, rows)
        for _ in range(c.reward_updates):  # r and d alone
            batch = self.real.sample(c.model_batch, gens)
            self.model.update(batch, gens, resample=resample, mdn=False, terminal_weight=weight)

    def _terminal_weight(self) -> torch.Tensor | None:
        """``terminal_weight`` balanced: per agent (P,), the transitions of M_R that are not
        terminal per terminal one (at least 1; 1 while it holds none): the weight that makes
        d's two classes weigh the same. None: as sampled."""
        if self.config.terminal_weight == "none":
            return None
        ends = self.real.data["done"].sum(1)  # unheld slots hold 0
        held = torch.as_tensor(self.real.size, device=ends.device, dtype=ends.dtype)
        return torch.where(ends > 0, (held - ends) / ends.clamp(min=1), 1.0).clamp(min=1.0)

    def _start_episodes(self) -> None:
        """Reset the envs of the agents starting an episode (each seeded as its spec says), and
        those of stopped agents that ended one (a vector env steps all its copies)."""
        starting = [i for i in range(self.size) if self.active[i] and self._starting[i]]
        idle = [i for i in range(self.size) if not self.active[i] and self._env_done[i]]
        if not starting and not idle:
            return
        mask = np.zeros(self.size, dtype=bool)
        mask[starting + idle] = True
        seeds = [
            self.spec.reset_seed(c.seed, e) for c, e in zip(self.configs, self.episode, strict=True)
        ]
        obs, info = self.envs.reset(seed=seeds, options={"reset_mask": mask})
        self._env_done[mask] = False
        if not starting:
            return
        rows = torch.as_tensor(starting, device=self.device)
        x, extra = self.spec.encoder_input(obs, info)
        self.mu[rows], self.sigma[rows] = self._encode(starting, x, extra)
        for i in starting:
            self._starting[i] = False
            self._episode[i] = EpisodeTotals()

    def _encode(self, agents: list[int], x, extra) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder's posterior of the agents' observations (``x``, ``extra``: what the
        spec's :meth:`~imagine.envs.spec.EnvSpec.encoder_input` reads from a step)."""
        mu, sigma = self.encoder.encode(x[agents], None if extra is None else extra[agents])
        return mu.to(self.device), sigma.to(self.device)

    def _controller_states(
        self, batch: dict[str, torch.Tensor], gens: list[torch.Generator | None]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The states C learns from for a real batch: V's means, or draws from N(mu, sigma)."""
        if self.config.controller_input == "mu":
            return batch["mu"], batch["next_mu"]
        z = agent_normal(batch["mu"], batch["sigma"], gens)
        return z, agent_normal(batch["next_mu"], batch["next_sigma"], gens)

    def _learn_from_real(self, agents: list[int], updates: int, key: str) -> None:
        """Lines 14-15: ``updates`` C updates of ``agents`` on real batches from M_R."""
        if not agents:
            return
        gens = [g if i in agents else None for i, g in enumerate(self.generators)]
        rows = torch.as_tensor(agents, device=self.device)
        c = self.config
        expanding = [i for i in agents if self._expands(i)]
        expanding_rows = torch.as_tensor(expanding, dtype=torch.int64, device=self.device)
        for _ in range(updates):
            b = self.real.sample(c.real_batch, gens)
            z, next_z = self._controller_states(b, gens)
            target = None
            if expanding:  # value expansion through M from I_start on, equation 1 before
                target = self.controller.td_target(b["reward"], next_z, b["done"])
                if c.value_expansion_weighting == "steve":
                    expanded, horizon = steve_target(self.controller, self.model, z,
                                                     b["action"], b["reward"], next_z,
                                                     b["done"], c.value_expansion)  # fmt: skip
                    self._record("charts/expansion_horizon", horizon, expanding_rows)
                else:
                    expanded = expanded_target(self.controller, self.model, b["reward"],
                                               next_z, b["done"], c.value_expansion,
                                               c.value_expansion_members)  # fmt: skip
                target[expanding] = expanded[expanding]
            loss = self.controller.update(z, b["action"], b["reward"], next_z, b["done"], agents,
                                          target)  # fmt: skip
            self._record(key, loss, rows)

    def _expands(self, agent: int) -> bool:
        """Whether the agent's real targets are expanded through M now: with value expansion,
        from I_start on, and with ``imagination_fallback`` only while M is trusted."""
        c = self.config
        if not c.value_expansion or self.episode[agent] < c.imagination_start:
            return False
        return not c.imagination_fallback or self._trusted(agent)

    def _switched(self, agent: int) -> bool:
        """Whether ``imagination_actions_until`` has switched the agent to the paper's
        rollouts (ungated, M never judged)."""
        c = self.config
        return actions_at(c, self.episode[agent]) != c.imagination_actions

    def _trusted(self, agent: int) -> bool:
        """Whether M counts as trusted for the agent: its trust test's last judgment, or
        switched to the paper's rollouts, which trust M without judging it."""
        return self.trust.trusted[agent] or self._switched(agent)

    def _imagine(self, live: list[int], eps: list[float]) -> None:
        """Lines 16-20 for the agents past their I_start: imagine, store in M_I what the
        agent's gate keeps (all without one), make N_I updates of C on M_I (with
        ``imagination_adaptive``, as many as its acceptance and M's trust allow;
        :mod:`imagine.learning.gate`)."""
        c = self.config
        if c.method != "augmented":
            return
        imagining = [i for i in live if self.episode[i] >= c.imagination_start]
        if not imagining:
            return
        # with the fallback an untrusted M's rollouts would teach C nothing: none are made
        rolling = [i for i in imagining if self.t[i] % c.imagination_every == 0
                   and (not c.imagination_fallback or self._trusted(i))]  # fmt: skip
        if rolling:
            self._roll_out(rolling, eps)
        updates = self._imaginary_updates(imagining)
        gens = [g if i in imagining else None for i, g in enumerate(self.generators)]
        made = dict.fromkeys(imagining, 0)
        for j in range(c.n_imaginary_updates):
            # agents with updates left and something in M_I (a gate may have kept nothing yet)
            learning = [i for i in imagining if updates[i] > j and self.imaginary.size[i] > 0]
            if not learning:
                break
            if learning != imagining:
                gens = [g if i in learning else None for i, g in enumerate(self.generators)]
            rows = torch.as_tensor(learning, device=self.device)
            b = self.imaginary.sample(c.imaginary_batch, gens)
            loss = self.controller.update(
                b["z"], b["action"], b["reward"], b["next_z"], b["done"], learning
            )
            self._record("losses/controller_imaginary", loss, rows)
            for i in learning:
                made[i] += 1
        if c.imagination_fallback:
            self._fall_back(made)

    def _fall_back(self, made: dict[int, int]) -> None:
        """``imagination_fallback``: each agent's imaginary updates not made this step, made on
        real batches (agents with as many left learn together)."""
        left = {i: self.config.n_imaginary_updates - n for i, n in made.items()}
        for n in sorted(set(left.values()) - {0}):
            agents = [i for i, m in left.items() if m == n]
            self._learn_from_real(agents, n, "losses/controller_real_extra")

    def _roll_out(self, imagining: list[int], eps: list[float]) -> None:
        """Lines 16-18 for ``imagining``: I_B rollouts each, stored in M_I as far as the
        agent's gate keeps them."""
        c = self.config
        gens = [g if i in imagining else None for i, g in enumerate(self.generators)]
        mu, sigma = self._imagination_starts(gens)
        scale = posterior_scale(sigma)  # V's, before M's inputs lose it
        if c.model_latents == "mu":
            sigma = torch.zeros_like(sigma)
        if c.imagination_epsilon >= 0:
            eps = [c.imagination_epsilon] * self.size
        actions = {i: actions_at(c, self.episode[i]) for i in imagining}
        rollouts: list[dict[str, torch.Tensor] | None] = [None] * self.size
        for kind in sorted(set(actions.values())):  # one batch per kind of imagination
            drawing = [g if actions.get(i) == kind else None for i, g in enumerate(gens)]
            made = imagine_rollouts(
                self.imagined_by, self.controller, mu, sigma, c.imagination_breadth,
                c.imagination_depth, eps, drawing, draw=c.imagination_draw, scale=scale,
                actions=kind,
            )  # fmt: skip
            rollouts = [m if actions.get(i) == kind else r
                        for i, (m, r) in enumerate(zip(made, rollouts, strict=True))]  # fmt: skip
        for i in imagining:
            transitions = rollouts[i]
            disagreement = transitions.pop("disagreement")
            rollout, step = transitions.pop("rollout"), transitions.pop("step")
            totals = self._episode[i]
            totals.imagined += len(disagreement)
            if c.imagination_actions != actions[i]:  # switched: the paper's imagination, ungated
                self.imaginary.add(i, **transitions)
                continue
            if c.imagination_uncertainty == "support":
                disagreement = self._support(i, transitions["z"], transitions["action"])
            if c.model_ensemble > 1 or c.imagination_uncertainty == "support":
                totals.add_disagreement(float(disagreement.sum()))
            if self.trust.on:
                keep = self.trust.gate(i, disagreement, rollout, step, gens[i])
                if c.imagination_gate != "none":
                    transitions = {key: value[keep] for key, value in transitions.items()}
                    totals.add_accepted(len(transitions["z"]))
            self.imaginary.add(i, **transitions)

    def _support(self, agent: int, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The support distance of an agent's imagined transitions to its M_R
        (:func:`imagine.learning.gate.support_distance`)."""
        held = self.real.size[agent]
        return support_distance(z, action, self.real.data["mu"][agent, :held],
                                self.real.data["action"][agent, :held])  # fmt: skip

    def _imaginary_updates(self, agents: list[int]) -> dict[int, int]:
        """N_I of each agent this step: the config's, or with ``imagination_adaptive`` N_I
        times its running acceptance, 0 while M is not trusted (:mod:`imagine.learning.gate`).
        An agent that ``imagination_actions_until`` has switched to the paper's rollouts
        (ungated, so no acceptance of its own) makes the config's N_I."""
        c = self.config
        if not c.imagination_adaptive:
            return {i: c.n_imaginary_updates for i in agents}
        switched = [i for i in agents if self._switched(i)]
        agents = [i for i in agents if i not in switched]
        due = [i for i in agents if self.trust.due(i, self.t[i])]
        if due:  # one batched judgment of the whole population, kept for the agents due
            recent, held = self.real.newest_each(TRUST_RECENT)
            if c.imagination_trust_test == "step":
                right = one_step_close(self.model, recent, held,
                                       c.imagination_trust_tolerance).tolist()  # fmt: skip
            else:
                right = one_step_right(self.model, recent, held, self.n_actions).tolist()
            if c.imagination_trust_terminals:  # d judged too: the lower of the two shares
                d_right = terminal_right(self.model, self.real, c.imagination_trust_terminals)
                right = [min(a, b) for a, b in zip(right, d_right.tolist(), strict=True)]
            for i in due:
                self.trust.judge(i, self.t[i], right[i])
        for i in agents:
            self._episode[i].add_trust(self.trust.trusted[i])
        return {
            i: imaginary_updates(c.n_imaginary_updates, self.trust.acceptance[i],
                                 self.trust.trusted[i])
            for i in agents
        } | {i: c.n_imaginary_updates for i in switched}  # fmt: skip

    def _imagination_starts(
        self, gens: list[torch.Generator | None]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The posteriors the rollouts start from: the current one, (P, latent_dim), or I_B
        states of M_R drawn uniformly, (P, I_B, latent_dim) (``imagination_from``)."""
        if self.config.imagination_from == "current":
            return self.mu, self.sigma
        starts = self.real.sample(self.config.imagination_breadth, gens)
        return starts["mu"], starts["sigma"]

    def _record(self, key: str, loss: torch.Tensor, rows: torch.Tensor) -> None:
        if key not in self._loss_sum:
            self._loss_sum[key] = torch.zeros(self.size, dtype=torch.float64, device=self.device)
            self._loss_count[key] = torch.zeros(self.size, dtype=torch.int64, device=self.device)
        self._loss_sum[key][rows] += loss[rows].double()
        self._loss_count[key][rows] += 1

    def _end_episode(self, i: int) -> dict[str, float] | None:
        """The finished episode's statistics and mean losses; None (and the agent stopped,
        with a failure) if a loss became non-finite."""
        stats = self._episode[i].stats()
        for key in self._loss_sum:
            n = int(self._loss_count[key][i])
            if n:
                stats[key] = float(self._loss_sum[key][i]) / n
            self._loss_sum[key][i] = 0.0
            self._loss_count[key][i] = 0
        for key, value in stats.items():
            if key in NETWORK_OF and not np.isfinite(value):
                self.failures[i] = (
                    f"{NETWORK_OF[key]} loss became {value} at real time step {self.t[i]} "
                    f"(episode {self.episode[i]}); the run keeps its last checkpoint"
                )
                self.stop(i)
                return None
        return stats

    # --- one agent's networks and checkpoints -------------------------------------------------

    def networks(self, agent: int) -> tuple[Controller, WorldModel]:
        """Copies of agent ``agent``'s C and M as single-agent modules (on the CPU)."""
        controller, model = copy.deepcopy(self.templates)
        export_agent(self.controller.q, agent, controller.q.to(self.device))
        self.model.export_agent(agent, model.to(self.device))
        return controller.cpu().eval(), model.cpu().eval()

    def agent_state(self, agent: int) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Everything agent ``agent`` needs to continue exactly where it is: tensors (C and
        its target, M, both Adam states, both memories, the gate, its generator) and plain
        values (episode and step counts, its environment stream, its config, the device);
        :mod:`imagine.learning.agent_checkpoint` writes them to its run folder."""
        controller, model = self.networks(agent)
        tensors = {f"controller.{k}": v for k, v in controller.state_dict().items()}
        if self.controller.target is not None:
            target = export_agent(self.controller.target, agent, copy.deepcopy(controller.q))
            tensors |= {f"controller_target.{k}": v for k, v in target.state_dict().items()}
        tensors |= self.controller.optimizer.agent_state(agent, "controller_optim")
        tensors |= {f"model.{k}": v for k, v in model.state_dict().items()}
        tensors |= self.model.optimizer.agent_state(agent, "model_optim")
        tensors |= self.real.state_dict("real", agent) | self.imaginary.state_dict(
            "imaginary", agent
        )
        if self.trust.on:
            tensors |= self.trust.state_dict("gate", agent)
        tensors["rng.generator"] = self.generators[agent].get_state()
        values = {
            "episode": self.episode[agent], "t": self.t[agent],
            "controller_updates": int(self.controller.updates[agent]),
            "env_rng": self.spec.env_state(self.envs, agent),
            "config": dataclasses.asdict(self.configs[agent]), "device": self.device.type,
        }  # fmt: skip
        return tensors, values

    def set_agent_state(
        self, agent: int, tensors: dict[str, torch.Tensor], values: dict[str, Any], where: str
    ) -> None:
        """Agent ``agent`` as :meth:`agent_state` gave it (it starts its next episode);
        ``where`` names the file in errors."""
        if values.get("device", "cpu") != self.device.type:  # generator states differ
            raise CheckpointError(
                f"{where} was trained on {values.get('device', 'cpu')}; resume it with --device "
                f"{values.get('device', 'cpu')}"
            )
        controller, model = copy.deepcopy(self.templates)
        load_state_dict_strict(controller, part(tensors, "controller"), where)
        load_state_dict_strict(model, part(tensors, "model"), where)
        import_agent(self.controller.q, agent, controller.q.to(self.device))
        self.model.import_agent(agent, model.to(self.device))
        if self.controller.target is not None:
            load_state_dict_strict(controller.q, part(tensors, "controller_target"), where)
            import_agent(self.controller.target, agent, controller.q.to(self.device))
        self.controller.optimizer.load_agent_state(agent, tensors, "controller_optim")
        self.model.optimizer.load_agent_state(agent, tensors, "model_optim")
        self.real.load_state_dict(tensors, "real", agent)
        self.imaginary.load_state_dict(tensors, "imaginary", agent)
        if self.trust.on:
            self.trust.load_state_dict(tensors, "gate", agent)
        self.generators[agent].set_state(tensors["rng.generator"])
        self.spec.set_env_state(self.envs, agent, values["env_rng"])
        self.episode[agent], self.t[agent] = int(values["episode"]), int(values["t"])
        self.controller.updates[agent] = int(values["controller_updates"])
        self._starting[agent] = True

    def start_dynamics_from(self, agent: int, tensors: dict[str, torch.Tensor], where: str) -> None:
        """Agent ``agent``'s MDN member(s) from another run's checkpoint tensors
        (``init_from``): its r, d and C keep their fresh weights; M's optimizer state is fresh
        for all."""
        model = self.model.export_agent(agent, copy.deepcopy(self.templates[1]))
        saved = part(tensors, "model")
        load_state_dict_strict(model.mdn, part(saved, "mdn"), where)
        load_state_dict_strict(model.more_mdns, part(saved, "more_mdns"), where)
        self.model.import_agent(agent, model.to(self.device))


def part(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors under ``prefix.``, with the prefix taken off."""
    return {k[len(prefix) + 1 :]: v for k, v in tensors.items() if k.startswith(prefix + ".")}


@dataclasses.dataclass
class EpisodeTotals:
    """What one agent's running episode has gathered so far."""

    total: float = 0.0
    length: int = 0
    success: bool | None = None
    """Whether the goal was reached (None: the environment does not say)."""
    imagined: int = 0
    """Transitions imagined, before any gate."""
    disagreement: float | None = None
    """Sum of M's members' disagreement over the imagined transitions (None: one member)."""
    accepted: int | None = None
    """Imagined transitions a gate kept (None: no gate)."""
    trusted: int = 0
    """Imagination steps with M trusted (``imagination_adaptive``)."""
    judged: int = 0
    """Imagination steps of an adaptive agent (0: not adaptive)."""
    eps: float = 0.0

    def add(self, reward: float, eps: float, success: bool | None) -> None:
        self.total += reward
        self.length += 1
        if success is not None:
            self.success = bool(self.success) or success
        self.eps = eps

    def add_disagreement(self, total: float) -> None:
        self.disagreement = (self.disagreement or 0.0) + total

    def add_accepted(self, n: int) -> None:
        self.accepted = (self.accepted or 0) + n

    def add_trust(self, trusted: bool) -> None:
        self.trusted += int(trusted)
        self.judged += 1

    def stats(self) -> dict[str, float]:
        out = {"charts/return": self.total}
        if self.success is not None:  # the environment says when a goal is reached
            out["charts/success"] = float(self.success)
        out |= {"charts/episode_length": float(self.length), "charts/epsilon": self.eps,
                "charts/imagined_transitions": float(self.imagined)}  # fmt: skip
        if self.disagreement is not None and self.imagined:
            out["charts/imagined_disagreement"] = self.disagreement / self.imagined
        if self.accepted is not None and self.imagined:
            out["charts/imagined_accepted"] = self.accepted / self.imagined
        if self.judged:
            out["charts/model_trusted"] = self.trusted / self.judged
        return out
