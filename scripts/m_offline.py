"""Train fresh world models M offline on the real memory of an agent run and compare variants:
the cheap way to tell which of M's settings makes it right on V's latents (issue 14).

    .venv/bin/python scripts/m_offline.py RUN [RUN ...] [--updates 4000] [--batch 128] \
        [--variants "samples, change of state, 20% dropout" ...]

For each run (its last checkpoint: real memory M_R, V, task) and each variant (M's latents:
samples of N(mu, sigma) or V's means; M's mean head: the next state or its change; dropout in
all three of M's networks; the MDN's covariance, diagonal or full; the network its scales are
fitted on, with or without dropout's masks), trains a fresh M (seed 0)
with ``--updates`` Adam steps on batches from that memory and prints M's accuracy as `imagine
evaluate` measures it: the most likely next state on the non-terminal transitions, a sample of
M on the same, and the most likely next state from the terminal states M never trained on
(generalization), from their reference latents and from one fresh image of each (the
paper's test, over every terminal state and action; ``imagine.study.generalization``).

``--input-noise C [C ...]``: each variant also trained with its *inputs* drawn from V's
posterior widened by C times M_R's per-dimension spread of mu (sigma^2 + (C s)^2; the
targets keep V's posterior; samples variants only): does an M taught to ignore where an
image lies in its macrostate's cloud (its jitter, `scripts/m_jitter.py`) generalize better
from fresh images?
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from imagine.checkpoint import load_tensors
from imagine.envs.gesture_puzzle.evaluation import model_accuracy
from imagine.learning.agent import load_agent
from imagine.learning.memory import ReplayMemory, real_fields
from imagine.models.world_model import PopulationWorldModel, WorldModel

# fmt: off
VARIANTS = {  # name: (re-sample latents from N(mu, sigma), residual mean head, dropout in M,
    #                  the MDN's covariance[, the network its scales are fitted on])
    "samples, next state (paper)": (True, False, 0.0, "diagonal"),
    "samples, change of state": (True, True, 0.0, "diagonal"),
    "means, next state": (False, False, 0.0, "diagonal"),
    "means, change of state": (False, True, 0.0, "diagonal"),
    "samples, next state, 50% dropout": (True, False, 0.5, "diagonal"),
    "samples, change of state, 50% dropout": (True, True, 0.5, "diagonal"),
    "samples, change of state, 20% dropout": (True, True, 0.2, "diagonal"),
    "samples, change of state, 20% dropout, full covariance": (True, True, 0.2, "full"),
    "means, change of state, 20% dropout": (False, True, 0.2, "diagonal"),
    "means, change of state, 20% dropout, full covariance": (False, True, 0.2, "full"),
    "samples, change of state, full covariance": (True, True, 0.0, "full"),
    "means, change of state, full covariance": (False, True, 0.0, "full"),
    "samples, next state, 50% dropout, clean scales": (True, False, 0.5, "diagonal", "clean"),
    "samples, change of state, 20% dropout, clean scales": (True, True, 0.2, "diagonal", "clean"),
    "samples, change of state, 20% dropout, full covariance, clean scales":
        (True, True, 0.2, "full", "clean"),
    "means, change of state, 20% dropout, clean scales": (False, True, 0.2, "diagonal", "clean"),
    "means, change of state, 20% dropout, full covariance, clean scales":
        (False, True, 0.2, "full", "clean"),
    "samples, next state, 20% dropout, full covariance, clean scales":
        (True, False, 0.2, "full", "clean"),
    "samples, change of state, full covariance, clean scales": (True, True, 0.0, "full", "clean"),
}
# fmt: on


def real_memory(run: Path, latent_dim: int) -> ReplayMemory:
    tensors = load_tensors(run / "agent.safetensors", "agent checkpoint")
    size = int(tensors["real._counters"][1])
    memory = ReplayMemory(size, real_fields(latent_dim))
    memory.load_state_dict(tensors, "real")
    return memory


def train_m(memory: ReplayMemory, latent_dim: int, updates: int, batch: int, resample: bool,
            residual: bool, dropout: float, covariance: str,
            scales: str = "dropout", input_noise: float = 0.0) -> WorldModel:  # fmt: skip
    spread = input_noise * memory.data["mu"][0, : len(memory)].std(0)
    torch.manual_seed(0)
    model = WorldModel(latent_dim, dropout=dropout, reward_hidden=128, residual=residual,
                       covariance=covariance, scales=scales)  # fmt: skip
    population = PopulationWorldModel([model])
    generator = torch.Generator().manual_seed(0)
    for _ in range(updates):
        sample = memory.sample(batch, [generator])
        if input_noise:
            sample["sigma"] = (sample["sigma"].square() + spread.square()).sqrt()
        population.update(sample, [generator], resample=resample)
    from imagine.models.stacked import export_agent

    return export_agent(population, 0, model).eval()


def fresh_generalization(agent, model: WorldModel) -> float:
    """``model``'s most likely next state right from one fresh image of each terminal state,
    every action (:func:`imagine.study.generalization.generalization`'s ``all`` row)."""
    from types import SimpleNamespace

    from imagine.study.generalization import generalization

    probe = SimpleNamespace(encoder=agent.encoder, model=model, config=agent.config)
    return generalization(probe)["all_terminal_accuracy"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--updates", type=int, default=4000)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument(
        "--variants",
        nargs="+",
        default=list(VARIANTS),
        choices=list(VARIANTS),
        metavar="NAME",
        help="the variants to train (default: all)",
    )
    parser.add_argument(
        "--input-noise",
        nargs="+",
        type=float,
        default=[0.0],
        metavar="C",
        help="also train each variant with inputs widened by C x M_R's spread of mu",
    )
    parser.add_argument(
        "--jitter",
        action="store_true",
        help="also print each M's jitter against the next state's cloud (scripts/m_jitter.py)",
    )
    args = parser.parse_args()
    means = [name for name in args.variants if not VARIANTS[name][0]]
    if any(args.input_noise) and means:
        parser.error(
            f"--input-noise widens V's posterior, so samples variants only, not {means[0]!r}"
        )
    torch.set_num_threads(1)
    labels = [(name, c, name if c == 0 else f"{name}, input noise {c:g}")
              for name in args.variants for c in args.input_noise]  # fmt: skip
    results: dict[str, list[tuple[float, ...]]] = {label: [] for *_, label in labels}
    for run in args.runs:
        agent = load_agent(run)
        memory = real_memory(run, agent.encoder.latent_dim)
        print(f"{run}: {agent.episode} episodes, {len(memory)} real transitions", flush=True)
        for name, c, label in labels:
            model = train_m(memory, agent.encoder.latent_dim, args.updates, args.batch,
                            *VARIANTS[name], input_noise=c)  # fmt: skip
            a = model_accuracy(model, agent.encoder, agent.config.task)
            general = a["transition_terminal"]
            fresh = fresh_generalization(agent, model)
            results[label].append((a["transition_nonterminal"], a["transition_sampled"], general,
                                   fresh))  # fmt: skip
            print(f"  {label}: most likely {a['transition_nonterminal']:.1%}, sampled "
                  f"{a['transition_sampled']:.1%}, from terminal states {general:.1%} "
                  f"(fresh images {fresh:.1%})", flush=True)  # fmt: skip
            if args.jitter:
                from m_jitter import measure

                m = measure(agent, 16, model, sample=VARIANTS[name][0])
                fresh = m["draws right from fresh images"]
                print(f"    draws right from fresh images {fresh:.1%}; "
                      + "; ".join(f"{k} " + " ".join(f"{x:.2f}" for x in m[k].tolist())
                                  for k in ("cloud", "jitter", "scales")), flush=True)  # fmt: skip
    print(f"\n| M trained offline ({args.updates} x {args.batch}) | most likely, non-terminal | "
          "sampled, non-terminal | most likely, from terminal states | the same from fresh "
          "images |")  # fmt: skip
    print("| --- | --- | --- | --- | --- |")
    for name, rows in results.items():
        x = 100 * np.array(rows)
        cells = [f"{m:.1f} ({s:.1f})" for m, s in zip(x.mean(0), x.std(0, ddof=1) if len(x) > 1
                                                       else np.zeros(4), strict=True)]  # fmt: skip
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
