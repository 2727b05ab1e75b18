"""Model trust (issue 15): which imagined transitions reach M_I, and how many imaginary C
updates a step makes, decided by M's own signals and no per-task number.

**Gates** (``imagination_gate``) judge each step's rollouts after they are imagined (the
rollouts themselves, and every random draw in them, are those of an ungated agent). With u a
transition's uncertainty (``imagination_uncertainty``) and the threshold

    tau = imagination_gate_scale * quantile_q(U_1),   q = imagination_gate_quantile,

U_1 the first-step disagreements of the agent's last ``imagination_gate_window`` rollouts,
this step's included (linear interpolation between order statistics, ``torch.quantile``):

- ``stop``, as MACURA (Frauenknecht et al. 2024, "Trust the Model Where It Trusts Itself"):
  a rollout ends at its first transition with u > tau; that transition and all after it are
  not kept. A first step starts at a real state, so U_1 is how unsure M is where it has data;
  a rollout is trusted while it stays that sure (MACURA's threshold is likewise a quantile of
  first-step uncertainties, scaled).
- ``mask``, as M2AC (Pan et al. 2020, "Trust the Model When It Is Confident"): each
  transition with u > tau is dropped and the rollout goes on (M2AC keeps a fixed fraction of
  the most certain transitions; here the fraction follows tau).
- ``random``, the control: from the same transitions it drops as many as ``mask`` would,
  drawn uniformly without replacement from the agent's generator, so a study can tell the
  selection from the mere loss of imagined data. Its "current acceptance rate" is thus
  exactly ``mask``'s on the very same transitions.
- ``none``: everything is kept (the paper).

**Uncertainty** u of an imagined transition (z, a, z'), either

- ``disagreement``: the members' mean pairwise distance between their modes of z'
  (:mod:`imagine.learning.imagination`; K >= 2), or
- ``support``: how far M extrapolates from its data, the distance from z to the nearest start
  latent of a real transition with the same action in the agent's M_R,

      u = min_{j : a_j = a} || z - mu_j ||_2      (:func:`support_distance`).

  An MDN that has seen (s, a) predicts it; the wrong imagined transitions are mostly where C's
  greedy choice in imagination takes an action the agent never took from a state like z, and
  the members of an ensemble trained on the same data can agree on a wrong extrapolation
  there. Measured on the fast preset's agents (docs/research/model-trust.md), u
  detects wrong imagined states better than the members' disagreement, and it needs no
  ensemble.

The acceptance of a step is the share of its imagined transitions kept; the agent's
**running acceptance** a is their running mean over its imagination steps,
a <- a + (x - a) / min(n, :data:`ACCEPTANCE_HORIZON`) at its n-th step (the plain mean at
first, then an exponential mean over about that many steps); 1 without a gate.

**Adaptive imaginary ratio** (``imagination_adaptive``): a step makes

    N_I' = 0                        while M is not trusted,
    N_I' = floor(N_I * a + 1/2)     otherwise (N_I * a, rounded half up),

M being trusted when (judged every ``imagination_trust_every`` real time steps; the last
judgment holds in between), on the agent's newest :data:`TRUST_RECENT` real transitions of M_R, at
least ``imagination_trust_floor`` of its members' one-step predictions are right. With
``imagination_trust_test`` step, right is *near the observed next state*: within
``imagination_trust_tolerance`` of the real step's length (:func:`one_step_close`; for state
observations, where M can be wrong on most transitions and still tell the actions apart: an
Acrobot-v1 M that identifies the action on 93% of held-out transitions lands within a tenth of
the step on 46%). With action (the default), right is to *identify the action*:
the member's mode for (mu_t, a_t) lies nearer the observed mu_{t+1} than its mode for any
other action from mu_t (a tie of n actions counts 1 / n). The test needs no unit: one image of a
macrostate may lie farther from that macrostate's mean latent than V's posterior sigma by an
order of magnitude (V encodes which fragment it shows; docs/research/v-fit-for-dynamics.md,
round 3), so "within a few sigmas of the observed next latent" can fail for an M that names
the right macrostate every time; an M that does not yet tell the actions' consequences
apart identifies about 1 / actions of them.

With ``imagination_trust_terminals`` n > 0, d is judged as well (:func:`terminal_right`): M
is trusted only while d also calls at least the floor's share of the newest n real terminal
transitions of M_R terminal, and of the newest others not terminal. The one-step tests judge
the next state alone, and an M whose d misses the rare failures imagines rollouts that go on
past them (CartPole-v1 at 2500 steps: next state right on 99.8-100% of held-out transitions,
d on 40-85% of the failures; docs/suite.md, round 4).

**Fallback** (``imagination_fallback``): the N_I - N_I' imaginary updates an adaptive agent
does not make are made on real batches of M_R, and C's real targets are not expanded through M
while M is not trusted. An agent whose M is never trusted makes exactly the replay-ratio
control's updates (the baseline with the augmented agent's C and as many updates a step), so
where M is wrong imagination falls back to replay instead of to one update a step.
"""

from __future__ import annotations

import math

import torch

from imagine.config import GATES, AgentConfig
from imagine.errors import CheckpointError
from imagine.learning.memory import ReplayMemory

ACCEPTANCE_HORIZON = 100
"""Imagination steps over which the running acceptance averages (at most)."""

TRUST_RECENT = 100
"""Newest real transitions on which M's one-step prediction is judged."""

TIE = 1e-6
"""Distances this close to the nearest count as nearest (actions with the same outcome)."""


FAR = 1e6
"""The support distance of a transition whose action M_R does not hold at all. It enters the
ring of first steps like any other u, so while more than 1 - q of the recent first steps are
FAR (M_R lacks actions: only with an I_start near 0) tau is FAR-sized and the gate keeps them
too, as if it were off; once M_R holds every action (long before the presets' I_start) a FAR
transition is always dropped."""


def support_distance(
    z: torch.Tensor, action: torch.Tensor, memory_mu: torch.Tensor, memory_action: torch.Tensor
) -> torch.Tensor:
    """Per transition (z (N, D), action (N,)), the distance to the nearest start latent of the
    real transitions (memory_mu (M, D), memory_action (M,)) with the same action; :data:`FAR`
    where there is none."""
    if len(z) == 0 or len(memory_mu) == 0:
        return torch.full((len(z),), FAR, device=z.device)
    distance = torch.cdist(z, memory_mu)  # (N, M)
    other = action.unsqueeze(1) != memory_action.unsqueeze(0)
    return distance.masked_fill(other, FAR).min(-1).values.clamp(max=FAR)


def gate_threshold(first_steps: torch.Tensor, quantile: float, scale: float) -> torch.Tensor:
    """tau = scale * quantile_q(first-step disagreements) (0-d)."""
    return scale * torch.quantile(first_steps.float(), quantile)


def gate_transitions(
    rule: str,
    disagreement: torch.Tensor,
    rollout: torch.Tensor,
    step: torch.Tensor,
    threshold: torch.Tensor | float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Which of one agent's imagined transitions (N,) the gate ``rule`` keeps (bool (N,)),
    from their disagreement, the rollout each belongs to and its step in it; ``generator``
    draws ``random``'s choice."""
    over = disagreement > threshold
    if rule == "none":
        return torch.ones_like(over)
    if rule == "mask":
        return ~over
    if rule == "stop":  # kept while no transition of its rollout so far is over the threshold
        if len(step) == 0:
            return ~over
        # each rollout's first step over the threshold; past the last step for one never over
        first_over = torch.full((int(rollout.max()) + 1,), int(step.max()) + 1,
                                dtype=step.dtype, device=step.device)  # fmt: skip
        first_over.scatter_reduce_(0, rollout[over], step[over], "amin")
        return step < first_over[rollout]
    if rule == "random":
        keep = torch.ones_like(over)
        dropped = int(over.sum())
        if dropped:
            order = torch.randperm(len(over), generator=generator, device=generator.device)
            keep[order[:dropped].to(keep.device)] = False
        return keep
    raise ValueError(f"unknown gate {rule!r}; choose one of {', '.join(GATES)}")


def imaginary_updates(n: int, acceptance: float, trusted: bool) -> int:
    """N_I' of an adaptive agent: 0 while M is not trusted, else N_I * a rounded half up."""
    return math.floor(n * acceptance + 0.5) if trusted else 0


@torch.no_grad()
def one_step_right(
    model, recent: dict[str, torch.Tensor], valid: torch.Tensor, n_actions: int
) -> torch.Tensor:
    """Per agent (P,), the share of its members' one-step predictions on the real transitions
    ``recent`` ((P, N, ...) fields of M_R; ``valid`` (P, N) marks those held) that identify
    the action taken: the mode for a_t is (within :data:`TIE`) the nearest of the modes for
    all ``n_actions`` actions to the observed next mu; a tie of n actions counts 1 / n, so an
    M that ignores the action scores chance. 0 for an agent with none."""
    P, N, D = recent["mu"].shape
    z = recent["mu"].repeat_interleave(n_actions, dim=1)  # (P, N * A, D)
    actions = torch.arange(n_actions, device=z.device).repeat(N).expand(P, -1)
    modes = model.member_modes(z, actions)  # (P, K, N * A, D)
    K = modes.shape[1]
    modes = modes.view(P, K, N, n_actions, D)
    miss = (modes - recent["next_mu"][:, None, :, None]).norm(dim=-1)  # (P, K, N, A)
    taken = recent["action"].view(P, 1, N, 1).expand(P, K, N, 1)
    nearest = miss <= miss.min(-1, keepdim=True).values + TIE  # (P, K, N, A)
    right = nearest.gather(-1, taken).squeeze(-1) / nearest.sum(-1)  # a tie of n: 1 / n
    right = right * valid[:, None]
    return right.sum((-2, -1)) / (valid.sum(-1) * K).clamp(min=1)


@torch.no_grad()
def one_step_close(
    model, recent: dict[str, torch.Tensor], valid: torch.Tensor, tolerance: float
) -> torch.Tensor:
    """Per agent (P,), the share of its members' one-step predictions on the real transitions
    ``recent`` ((P, N, ...) fields of M_R; ``valid`` (P, N) marks those held) that land near
    the observed next state: ||mode_k(mu_t, a_t) - mu_{t+1}|| < tolerance * ||mu_{t+1} - mu_t||
    (``imagination_trust_test`` step; the probe's "next state" of
    :func:`imagine.envs.classic_control.extras.model_probe`). 0 for an agent with none."""
    modes = model.member_modes(recent["mu"], recent["action"])  # (P, K, N, D)
    K = modes.shape[1]
    miss = (modes - recent["next_mu"][:, None]).norm(dim=-1)  # (P, K, N)
    step = (recent["next_mu"] - recent["mu"]).norm(dim=-1)  # (P, N)
    right = (miss < tolerance * step[:, None]).float() * valid[:, None]
    return right.sum((-2, -1)) / (valid.sum(-1) * K).clamp(min=1)


@torch.no_grad()
def terminal_right(model, memory: ReplayMemory, n: int) -> torch.Tensor:
    """Per agent (P,), how right d is on real data (``imagination_trust_terminals``): the
    lower of its two shares, the newest ``n`` terminal transitions of M_R called terminal at
    their observed next state, and the newest :data:`TRUST_RECENT` others called not
    terminal. A share with no transition to judge is 1: an agent whose M_R holds no terminal
    yet is judged on the others alone."""
    ends, held_ends = memory.newest_where("done", n)
    recent, held = memory.newest_each(TRUST_RECENT)
    called = model.is_terminal(ends["next_mu"]).float()  # (P, n)
    recall = _share(called, held_ends)
    others = held & (recent["done"] == 0)
    return torch.minimum(recall, _share(1 - model.is_terminal(recent["next_mu"]).float(), others))


def _share(right: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The mean of ``right`` (P, N) over the ``valid`` rows of each agent; 1 where none are."""
    count = valid.sum(-1)
    share = (right * valid).sum(-1) / count.clamp(min=1)
    return torch.where(count > 0, share, torch.ones_like(share))


class ModelTrust:
    """Each agent's gate state: its ring of recent first-step disagreements and its running
    acceptance. Both go into the agent's checkpoint, so a resumed agent gates as one that
    never stopped."""

    def __init__(self, config: AgentConfig, agents: int, device: torch.device) -> None:
        self.config = config
        self.first_steps = ReplayMemory(
            config.imagination_gate_window, {"disagreement": ((), torch.float32)}, agents, device
        )
        self.acceptance = [1.0] * agents
        self.steps = [0] * agents
        self.trusted = [False] * agents
        self.judged_at = [-1] * agents  # the real time step of the last judgment; -1: never

    @property
    def on(self) -> bool:
        """Whether there is state to keep (a gate or the adaptive ratio)."""
        return self.config.imagination_gate != "none" or self.config.imagination_adaptive

    def due(self, agent: int, t: int) -> bool:
        """Whether the agent's trust is to be judged again at its real time step t."""
        last = self.judged_at[agent]
        return last < 0 or t - last >= self.config.imagination_trust_every

    def judge(self, agent: int, t: int, right: float) -> None:
        """Record a judgment: M is trusted while ``right`` reaches the floor."""
        self.trusted[agent] = right >= self.config.imagination_trust_floor
        self.judged_at[agent] = t

    def threshold(self, agent: int) -> torch.Tensor:
        """The agent's tau now."""
        c, ring = self.config, self.first_steps
        held = ring.data["disagreement"][agent, : ring.size[agent]]
        return gate_threshold(held, c.imagination_gate_quantile, c.imagination_gate_scale)

    def gate(
        self,
        agent: int,
        disagreement: torch.Tensor,
        rollout: torch.Tensor,
        step: torch.Tensor,
        generator: torch.Generator | None,
    ) -> torch.Tensor:
        """Record a step's first-step disagreements, then keep (bool (N,)) what the agent's
        gate keeps of its transitions; the running acceptance takes the step's share."""
        rule = self.config.imagination_gate
        if rule == "none":
            keep = torch.ones(len(disagreement), dtype=torch.bool, device=disagreement.device)
        else:
            self.first_steps.add(agent, disagreement=disagreement[step == 0])
            keep = gate_transitions(rule, disagreement, rollout, step, self.threshold(agent),
                                    generator)  # fmt: skip
        if len(keep):
            self.steps[agent] += 1
            x = float(keep.float().mean())
            self.acceptance[agent] += (x - self.acceptance[agent]) / min(
                self.steps[agent], ACCEPTANCE_HORIZON
            )
        return keep

    def state_dict(self, prefix: str, agent: int) -> dict[str, torch.Tensor]:
        tensors = self.first_steps.state_dict(f"{prefix}.first_steps", agent)
        running = [self.acceptance[agent], float(self.steps[agent])]
        tensors[f"{prefix}.acceptance"] = torch.tensor(running, dtype=torch.float64)
        judged = [float(self.trusted[agent]), float(self.judged_at[agent])]
        tensors[f"{prefix}.trust"] = torch.tensor(judged, dtype=torch.float64)
        return tensors

    def load_state_dict(self, tensors: dict[str, torch.Tensor], prefix: str, agent: int) -> None:
        self.first_steps.load_state_dict(tensors, f"{prefix}.first_steps", agent)
        if f"{prefix}.acceptance" not in tensors:
            raise CheckpointError(f"checkpoint lacks {prefix}.acceptance")
        acceptance, steps = tensors[f"{prefix}.acceptance"].tolist()
        self.acceptance[agent], self.steps[agent] = float(acceptance), int(steps)
        # a checkpoint from before trust was judged every few steps: judge at the next step
        trusted, judged_at = tensors.get(f"{prefix}.trust", torch.tensor([0.0, -1.0])).tolist()
        self.trusted[agent], self.judged_at[agent] = bool(trusted), int(judged_at)
