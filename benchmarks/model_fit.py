"""How well M's MDN fits a classic-control environment's dynamics, offline (issue 57).

    .venv/bin/python benchmarks/model_fit.py [--env Acrobot-v1] [--updates 3000]
        [--variant "no dropout" dropout=0] [--variant ...]

The `fast` preset's MDN (the reference) and each ``--variant`` (AgentConfig fields over the
preset, ``KEY=VALUE`` read as YAML) are trained, one torch thread, from the same seed on the
same 10,000 transitions of a uniform random policy (``random_transitions(env, 10000, seed=1)``)
for ``--updates`` Adam steps of the preset's batch size and learning rate, then judged on the
2000 held-out transitions of M's probe (seed 0; :func:`imagine.envs.classic_control.extras.
model_probe`): the share whose most likely next state is within a tenth of the true step's
length, and the median of error / step. Printed with each variant's ratio to the reference.

An RL run trains M on its own memory, which grows and follows C's policy; this isolates the
MDN's fit from that: an MDN that is wrong here on random transitions is wrong in the agent too.
"""

from __future__ import annotations

import argparse
import time

import torch
import yaml

from imagine.config import agent_preset
from imagine.envs.classic_control.true_model import random_transitions
from imagine.models.world_model import MDN


def tensors(rows) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(v, dtype=torch.int64 if k == "action" else torch.float32)
            for k, v in rows.items()}  # fmt: skip


def fit(env: str, updates: int, overrides: dict) -> tuple[float, float, float]:
    """(share within a tenth of the step, median error / step, seconds) of one MDN."""
    c = agent_preset("fast", **overrides)
    train = tensors(random_transitions(env, 10000, seed=1))
    test = tensors(random_transitions(env, 2000, seed=0))
    n_actions, dim = int(train["action"].max()) + 1, train["state"].shape[1]
    torch.manual_seed(c.seed)
    mdn = MDN(dim, n_actions, c.n_components, c.model_hidden, dropout=c.dropout,
              residual=c.model_residual)  # fmt: skip
    optimizer = torch.optim.Adam(mdn.parameters(), c.model_lr)
    draw = torch.Generator().manual_seed(c.seed)
    start = time.perf_counter()
    for _ in range(updates):
        i = torch.randint(len(train["state"]), (c.model_batch,), generator=draw)
        loss = mdn.loss(train["state"][i], train["action"][i], train["next"][i])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    mdn.eval()
    with torch.no_grad():
        guess = mdn.most_likely(test["state"], test["action"])
    step = (test["next"] - test["state"]).norm(dim=-1)
    error = (guess - test["next"]).norm(dim=-1)
    return float((error < 0.1 * step).float().mean()), float((error / step).median()), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="Acrobot-v1")
    parser.add_argument("--updates", type=int, default=3000)
    parser.add_argument("--variant", nargs="+", action="append", default=[],
                        metavar=("NAME", "KEY=VALUE"),
                        help="a name, then AgentConfig fields over the fast preset")  # fmt: skip
    args = parser.parse_args()
    torch.set_num_threads(1)
    variants = [("fast (reference)", {})]
    for name, *pairs in args.variant:
        variants.append((name, {k: yaml.safe_load(v) for k, v in (p.split("=", 1) for p in pairs)}))
    print(f"{args.env}, {args.updates} updates on 10000 random transitions; 2000 held out")
    print("| MDN | within 0.1 step | x reference | median error / step | s |")
    print("| --- | ---: | ---: | ---: | ---: |")
    reference = None
    for name, overrides in variants:
        right, median, seconds = fit(args.env, args.updates, overrides)
        reference = reference or right
        print(f"| {name} | {right:.1%} | {right / reference:.2f} | {median:.3f} | {seconds:.0f} |",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
