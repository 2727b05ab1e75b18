"""Networks of a population: P agents' copies of one architecture trained in one process.

Every weight carries a leading agent axis, (P, out, in), and a layer is one batched matrix
product (``torch.baddbmm``) over the agents, so P small networks cost a few large kernels
instead of P times as many small ones. Agent ``i``'s slice is computed exactly as it would be
alone: batched products work on each slice separately, so its numbers do not depend on which
other agents share the stack (``tests/test_population.py``).

What must stay per agent is kept per agent:

- randomness: dropout masks are drawn from each agent's own ``torch.Generator``;
- optimizer state: :class:`PopulationAdam` gives each agent's slices their own Adam state and
  step count, and an agent can sit out an update (its imaginary updates start at its own
  episode I_start);
- parameters: :func:`export_agent` and :func:`import_agent` move one agent's slices to and from
  the single-agent modules (:class:`~imagine.models.controller.Controller`,
  :class:`~imagine.models.world_model.WorldModel`), whose state dicts are what checkpoints hold.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import nn
from torch.nn import functional as F

from imagine.errors import CheckpointError


def linears(module: nn.Module) -> list[nn.Linear]:
    """The linear layers of a module, in registration order."""
    return [m for m in module.modules() if isinstance(m, nn.Linear)]


class StackedLinear(nn.Module):
    """P linear layers of the same shape: x (P, N, in) -> (P, N, out). The weight is kept as
    (P, in, out), the layout the batched product reads, so its gradient arrives in the
    parameter's own layout (an (out, in) weight used transposed gets a transposed gradient,
    which autograd then copies)."""

    def __init__(self, layers: Sequence[nn.Linear]) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.stack([layer.weight.detach().T for layer in layers]))
        self.bias = nn.Parameter(torch.stack([layer.bias.detach() for layer in layers]))
        self.compute_dtype: torch.dtype | None = None
        """The dtype of the batched product (None: the weights'). With ``torch.bfloat16`` the
        inputs, weights and bias are rounded to it for the product only: the weights, their
        gradients and Adam's state stay float32, and the output is float32 again, so losses,
        softmax and the MDN's log-likelihood are computed in float32 (mixed precision)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.shape[2] == 1:
            # one output unit: a product and a sum, because a batched product with a single
            # output column takes another kernel for one agent than for several, and rounds
            # differently (an agent's numbers would depend on the population's size)
            w = self.weight.transpose(1, 2)
            return (x * w).sum(-1, keepdim=True) + self.bias.unsqueeze(1)
        dtype = self.compute_dtype
        if dtype is None or dtype == x.dtype:
            return torch.baddbmm(self.bias.unsqueeze(1), aligned(x), self.weight)
        bias, weight = self.bias.unsqueeze(1).to(dtype), self.weight.to(dtype)
        return torch.baddbmm(bias, x.to(dtype), weight).to(x.dtype)


MATMUL_DTYPES = {"float32": None, "bfloat16": torch.bfloat16}
"""``AgentConfig.matmul_dtype``'s values and the product dtype each gives the stacked layers."""


def set_matmul_dtype(module: nn.Module, name: str) -> None:
    """Compute every :class:`StackedLinear` product in ``module`` in ``name``'s dtype
    (:data:`MATMUL_DTYPES`)."""
    for layer in module.modules():
        if isinstance(layer, StackedLinear):
            layer.compute_dtype = MATMUL_DTYPES[name]


ALIGN = 16
"""Floats in 64 bytes: where each agent's block of a matrix-product input must start."""


def aligned(x: torch.Tensor) -> torch.Tensor:
    """``x`` (P, N, in) with each agent's block starting on a 64-byte boundary (a copy with
    padding between agents when N * in is not a multiple of 16). The CPU's matrix-product
    kernels round differently for differently aligned operands, so without this an agent's
    few rows (one action, I_B imagined states) would give other numbers at an odd place in
    the stack than alone."""
    P, N, width = x.shape
    block = N * width
    if P == 1 or (block % ALIGN == 0 and x.is_contiguous()):
        return x
    stride = -(-block // ALIGN) * ALIGN
    buffer = x.new_empty(P, stride)
    buffer[:, :block] = x.reshape(P, block)
    return buffer[:, :block].view(P, N, width)


def agent_normal(
    mu: torch.Tensor, sigma: torch.Tensor, generators: Sequence[torch.Generator | None]
) -> torch.Tensor:
    """mu + sigma * noise for tensors (P, ...): agent i's standard normal noise is drawn from
    ``generators[i]`` (zero for an agent whose generator is None: it draws nothing)."""
    noise = torch.zeros_like(mu)
    for i, generator in enumerate(generators):
        if generator is not None:
            noise[i] = torch.randn(mu.shape[1:], generator=generator, device=mu.device)
    return mu + sigma * noise


def agent_dropout(
    x: torch.Tensor, p: float, generators: Sequence[torch.Generator | None]
) -> torch.Tensor:
    """Inverted dropout with each agent's mask drawn from its own generator (uniform draws
    below 1 - p: three times faster on a CPU than ``bernoulli_`` with a generator); an agent
    whose generator is None (not updating) draws nothing and keeps every unit."""
    keep = 1.0 - p
    # the mask holds 0 or 1 / keep: x * mask is then exactly (x * {0, 1}) * (1 / keep), in one
    # product instead of two (forward and backward). Each agent's uniform draws go straight into
    # its rows, and the comparison and the scale are then one pass over all agents (lt_ on a
    # float tensor leaves 1.0 or 0.0): the same numbers as a comparison per agent, and the
    # work around the draws halved (docs/benchmarks.md). Agents that draw nothing keep every unit.
    mask = torch.empty_like(x)
    idle = []
    for i, generator in enumerate(generators):
        if generator is None:
            idle.append(i)
        else:
            torch.rand(x.shape[1:], generator=generator, device=x.device, out=mask[i])
    mask.lt_(keep).mul_(1.0 / keep)
    for i in idle:
        mask[i] = 1.0
    return x * mask


class StackedMLP(nn.Module):
    """P copies of one :func:`~imagine.models.controller.mlp`: ReLU (then dropout, when generators
    are given) between layers, and after the last one too with ``activate_last``."""

    def __init__(
        self, mlps: Sequence[nn.Module], dropout: float = 0.0, activate_last: bool = False
    ) -> None:
        super().__init__()
        per_agent = [linears(m) for m in mlps]
        self.layers = nn.ModuleList(
            StackedLinear([agent[i] for agent in per_agent]) for i in range(len(per_agent[0]))
        )
        self.dropout = dropout
        self.activate_last = activate_last

    def forward(
        self, x: torch.Tensor, generators: Sequence[torch.Generator | None] | None = None
    ) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < last or self.activate_last:
                x = F.relu(x)
                if generators is not None and self.dropout > 0:
                    x = agent_dropout(x, self.dropout, generators)
        return x


def _pairs(stacked: nn.Module, module: nn.Module) -> list[tuple[StackedLinear, nn.Linear]]:
    """Each stacked layer with the single-agent layer it stands for (registration order)."""
    layers = [m for m in stacked.modules() if isinstance(m, StackedLinear)]
    return list(zip(layers, linears(module), strict=True))


@torch.no_grad()
def export_agent(stacked: nn.Module, agent: int, module: nn.Module) -> nn.Module:
    """Copy agent ``agent``'s slices into a single-agent module of the same architecture
    (linear layers registered in the same order); returns the module."""
    for s, m in _pairs(stacked, module):
        m.weight.copy_(s.weight[agent].T)
        m.bias.copy_(s.bias[agent])
    return module


@torch.no_grad()
def import_agent(stacked: nn.Module, agent: int, module: nn.Module) -> None:
    """Copy a single-agent module's parameters into agent ``agent``'s slices."""
    for s, m in _pairs(stacked, module):
        s.weight[agent].copy_(m.weight.T)
        s.bias[agent].copy_(m.bias)


class PopulationAdam:
    """Adam (torch's fused kernel) over stacked parameters with per-agent state.

    Each agent's slice of each parameter is a parameter of one ``torch.optim.Adam``, so every
    agent has its own moments and its own step count (the bias correction), exactly as with an
    Adam of its own. :meth:`step` takes the agents that update; the others' slices, moments and
    step counts stay as they are.

    ``members[j]``: the rows parameter j has per agent (default 1). An ensemble of K networks
    per agent is stacked agent-major, row ``i * K + k`` for agent i's member k; its members
    step together, as one agent's.
    """

    def __init__(
        self,
        params: Iterable[nn.Parameter],
        agents: int,
        lr: float,
        members: Sequence[int] | None = None,
    ) -> None:
        self.params = list(params)
        self.lr = lr
        counts = [1] * len(self.params) if members is None else list(members)
        # agent i's slices: member 0 of every parameter, then the other members, so that an
        # agent with one member keeps the state indices (checkpoint keys) it always had
        self.rows = [
            [(j, i * m) for j, m in enumerate(counts)]
            + [(j, i * m + k) for k in range(1, max(counts)) for j, m in enumerate(counts) if k < m]
            for i in range(agents)
        ]
        # detach(): the slices are leaves sharing the parameters' storage
        self.slices = [[self.params[j].detach()[r] for j, r in rows] for rows in self.rows]
        self.optimizer = torch.optim.Adam(
            [s for agent in self.slices for s in agent], lr=lr, fused=True
        )

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def step(self, agents: Sequence[int]) -> None:
        """One Adam step for ``agents`` from the gradients of the stacked parameters.

        The arithmetic is torch's fused Adam kernel on each chosen slice, exactly what
        ``self.optimizer.step()`` runs; the slices and their state are gathered here and handed
        to the kernel directly, which skips the optimizer's per-step bookkeeping over every
        slice of every agent (about a tenth of a `fast` step; docs/benchmarks.md). The state
        lives in ``self.optimizer.state`` as the optimizer keeps it (checkpoints read it)."""
        grads = [None if p.grad is None else p.grad.unbind(0) for p in self.params]
        slices, slice_grads, avgs, squares, steps = [], [], [], [], []
        for i in sorted(set(agents)):
            for (j, row), s in zip(self.rows[i], self.slices[i], strict=True):
                if grads[j] is None:
                    continue
                state = self.optimizer.state[s]
                if not state:  # as torch.optim.Adam initializes a fused slice's state
                    state["step"] = torch.zeros((), dtype=torch.float32, device=s.device)
                    state["exp_avg"] = torch.zeros_like(s, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(s, memory_format=torch.preserve_format)
                slices.append(s)
                slice_grads.append(grads[j][row])
                avgs.append(state["exp_avg"])
                squares.append(state["exp_avg_sq"])
                steps.append(state["step"])
        if not slices:
            return
        group = self.optimizer.param_groups[0]
        beta1, beta2 = group["betas"]
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            slices, slice_grads, avgs, squares, [], steps, amsgrad=False, lr=group["lr"],
            beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
            maximize=False, grad_scale=None, found_inf=None,
        )  # fmt: skip

    def agent_state(self, agent: int, prefix: str) -> dict[str, torch.Tensor]:
        """Agent ``agent``'s Adam state as ``{prefix}.{parameter index}.{name}`` tensors, in
        the stacked parameters' order and layout (weights (in, out))."""
        out = {}
        for index, s in enumerate(self.slices[agent]):
            for name, value in self.optimizer.state.get(s, {}).items():
                out[f"{prefix}.{index}.{name}"] = value.detach().cpu().clone()
        return out

    def load_agent_state(self, agent: int, tensors: dict[str, torch.Tensor], prefix: str) -> None:
        for index, s in enumerate(self.slices[agent]):
            names = ("step", "exp_avg", "exp_avg_sq")
            keys = [f"{prefix}.{index}.{name}" for name in names]
            if all(k in tensors for k in keys):
                for k in keys[1:]:
                    if tensors[k].shape != s.shape:
                        raise CheckpointError(
                            f"optimizer state {k} has shape {tuple(tensors[k].shape)}, "
                            f"expected {tuple(s.shape)}"
                        )
                self.optimizer.state[s] = {
                    name: tensors[k].to(s.device, torch.float32).clone()
                    if name == "step"
                    else tensors[k].to(s).clone()
                    for name, k in zip(names, keys, strict=True)
                }
            else:
                self.optimizer.state.pop(s, None)
