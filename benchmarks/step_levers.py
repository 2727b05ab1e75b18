"""The levers on a `fast` population step (issue 18), each against its reference in the same run.

    .venv/bin/python benchmarks/step_levers.py [--agents 5] [--steps 20] [--repeats 3]

Three populations of augmented `fast` agents (oracle encoder, imagination from the first step,
one torch thread) step in alternation, ``--steps`` lockstep steps at a time, ``--repeats``
times; the best milliseconds per step of each are printed with their ratio to the reference:

- *reference*: the code before the same-numbers levers (its dropout masks compared and scaled
  per agent, its Adam step through ``torch.optim.Adam.step`` over every agent's slices), kept
  here as it was;
- *today*: the library's code (masks compared and scaled in one pass over all agents, the
  slices handed to torch's fused Adam kernel directly);
- *d 2 x 128*: today's code with the d-network at 2 x 128 units (``terminal_hidden``), the
  one lever here that changes the numbers.

The reference and today's population start alike and take the same steps; at the end the
benchmark checks that their weights and Adam moments are bitwise equal (the levers' claim).
"""

from __future__ import annotations

import argparse
import time
import types

import torch

import imagine.models.stacked as stacked
from imagine.config import agent_preset
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.learning.population import Population

TODAY_DROPOUT = stacked.agent_dropout


def reference_dropout(x, p, generators):
    """agent_dropout before issue 18: a mask of ones, each agent's comparison and scale apart."""
    keep = 1.0 - p
    mask = torch.ones_like(x)
    for i, generator in enumerate(generators):
        if generator is not None:
            torch.mul(torch.rand(x.shape[1:], generator=generator, device=x.device) < keep,
                      1.0 / keep, out=mask[i])  # fmt: skip
    return x * mask


def reference_adam_step(self, agents) -> None:
    """PopulationAdam.step before issue 18: every slice's gradient set, then Adam.step()."""
    chosen = set(agents)
    for i, (rows, agent) in enumerate(zip(self.rows, self.slices, strict=True)):
        for (j, row), s in zip(rows, agent, strict=True):
            grad = self.params[j].grad
            s.grad = grad[row] if i in chosen and grad is not None else None
    self.optimizer.step()


def population(agents: int, **overrides) -> Population:
    settings = {"encoder": "oracle", "method": "augmented", "imagination_start": 0,
                "episodes": 10**6, **overrides}  # fmt: skip
    configs = [agent_preset("fast", seed=seed, **settings) for seed in range(agents)]
    pop = Population(configs, OracleEncoder())
    n, d = configs[0].model_batch, 8
    generator = torch.Generator().manual_seed(0)
    for i in range(agents):  # M_R needs a batch's worth before the first update
        pop.real.add(
            i, mu=torch.randn(n, d, generator=generator), sigma=torch.full((n, d), 0.05),
            action=torch.randint(6, (n,), generator=generator),
            next_mu=torch.randn(n, d, generator=generator), next_sigma=torch.full((n, d), 0.05),
            reward=torch.full((n,), -1.0), done=torch.zeros(n),
        )  # fmt: skip
    return pop


def use_reference(pop: Population, on: bool) -> None:
    stacked.agent_dropout = reference_dropout if on else TODAY_DROPOUT
    for optimizer in (pop.controller.optimizer, pop.model.optimizer):
        if on:
            optimizer.step = types.MethodType(reference_adam_step, optimizer)
        else:
            optimizer.__dict__.pop("step", None)


def seconds_per_step(pop: Population, steps: int, reference: bool) -> float:
    use_reference(pop, reference)
    try:
        start = time.perf_counter()
        for _ in range(steps):
            pop.step()
        return (time.perf_counter() - start) / steps
    finally:
        use_reference(pop, False)


def same_numbers(a: Population, b: Population) -> bool:
    for x, y in ((a.controller, b.controller), (a.model, b.model)):
        if any(not torch.equal(p, q) for p, q in zip(x.parameters(), y.parameters(), strict=True)):
            return False
    for agent in range(a.size):
        for x, y in ((a.model.optimizer, b.model.optimizer),
                     (a.controller.optimizer, b.controller.optimizer)):  # fmt: skip
            sa, sb = x.agent_state(agent, "o"), y.agent_state(agent, "o")
            if sa.keys() != sb.keys() or any(not torch.equal(sa[k], sb[k]) for k in sa):
                return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = {
        "reference (before issue 18)": (population(args.agents), True),
        "today": (population(args.agents), False),
        "today, d 2 x 128": (population(args.agents, terminal_hidden=128), False),
    }
    for pop, reference in rows.values():  # warm-up step (and imagination memories filled)
        seconds_per_step(pop, 1, reference)
    best = {name: float("inf") for name in rows}
    for _ in range(args.repeats):
        for name, (pop, reference) in rows.items():
            best[name] = min(best[name], seconds_per_step(pop, args.steps, reference))
    ref = best["reference (before issue 18)"]
    print(f"`fast` augmented population of {args.agents}, 1 thread, best of {args.repeats} x "
          f"{args.steps} lockstep steps each, alternated")  # fmt: skip
    print("| code | ms per lockstep step | reference / this |")
    print("| --- | --- | --- |")
    for name, seconds in best.items():
        print(f"| {name} | {1000 * seconds:.1f} | {ref / seconds:.2f}x |")
    same = same_numbers(rows["reference (before issue 18)"][0], rows["today"][0])
    print(f"reference and today bitwise equal after the same steps (weights, Adam state): {same}")


if __name__ == "__main__":
    main()
