"""Real time steps per second of Algorithm 1 for populations of 1, 5 and 20 agents, the cost of
one M update, and how close both come to the machine's peak FLOP rate.

For `fast` and `paper` (augmented, imagination from the first episode, oracle encoder so vision
does not count; V's cost is in vae_speed.py): each population is built, M_R gets a batch of
random transitions per agent, and ``--steps`` lockstep steps are timed after one warm-up step.
FLOPs are counted by ``torch.utils.flop_counter`` (matrix products, forward and backward) over
one step and one M update. The peak is a large matrix product timed in the same run, with the
same number of threads, in the dtype of the row's products. Every row is measured with float32
products and with bfloat16 ones (``matmul_dtype``: mixed precision, float32 weights and
losses; issue 18), one after the other in the same run (``--dtypes`` picks). The last lines:
peak memory of this process (it ends with the 20-agent `paper` population, the paper's whole
study in one process) and 1000 greedy test episodes through V (untrained weights; the cost
does not depend on them).

    .venv/bin/python benchmarks/population_speed.py [--threads 1] [--steps 20]
        [--presets fast,paper] [--dtypes float32,bfloat16] [--set model_ensemble=5 ...]
        [--compare model_ensemble=5 ...] [--device cuda]

``--set KEY=VALUE`` changes a setting of every agent (as `imagine train --set` does), e.g. the
ensemble size K of M's MDN. ``--compare KEY=VALUE`` (repeatable) measures every row twice in the
same run, the settings of ``--set`` alone (the reference) and with these on top, one right after
the other, and prints the second's step time as a multiple of the reference's: e.g. the cost of
the `fast` augmented agent's ensemble of five (issue 15 asks at most 2x), ``--set
model_ensemble=1 --set imagination_gate=none --compare model_ensemble=5 --compare
imagination_gate=mask``.

``--device cuda`` times the populations on a GPU (the peak is then the
GPU's float32 matrix product, TF32 off, and with TF32 on, timed in the same run); the V line
stays on the CPU.
"""

from __future__ import annotations

import argparse
import resource
import time
from typing import Any

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from imagine.config import agent_preset, parse_assignments
from imagine.devices import resolve_device
from imagine.envs.gesture_puzzle.encoders import OracleEncoder
from imagine.learning.population import Population


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_flops(
    n: int = 2048,
    repeats: int = 5,
    device: torch.device | None = None,
    dtype: torch.dtype = torch.float32,
) -> float:
    device = device or torch.device("cpu")
    if device.type == "cuda":
        n, repeats = 8192, 20
    a = torch.randn(n, n, device=device, dtype=dtype)
    b = torch.randn(n, n, device=device, dtype=dtype)
    a @ b
    synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    synchronize(device)
    return repeats * 2 * n**3 / (time.perf_counter() - start)


def population(
    preset: str, agents: int, overrides: dict[str, Any] | None = None, device: str = "cpu"
) -> Population:
    settings = {"encoder": "oracle", "method": "augmented", "imagination_start": 0,
                "episodes": 10**6, **(overrides or {})}  # fmt: skip
    configs = [agent_preset(preset, seed=seed, **settings) for seed in range(agents)]
    pop = Population(configs, OracleEncoder(), device)
    n, d = configs[0].model_batch * configs[0].model_ensemble, 8
    for i in range(agents):  # M_R needs a batch's worth before the first update
        pop.real.add(
            i, mu=torch.randn(n, d, device=device), sigma=torch.full((n, d), 0.05, device=device),
            action=torch.randint(6, (n,), device=device), next_mu=torch.randn(n, d, device=device),
            next_sigma=torch.full((n, d), 0.05, device=device),
            reward=torch.full((n,), -1.0, device=device), done=torch.zeros(n, device=device),
        )  # fmt: skip
    return pop


def timed(fn, repeats: int, device: torch.device | None = None) -> float:
    device = device or torch.device("cpu")
    synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    synchronize(device)
    return (time.perf_counter() - start) / repeats


def flops_of(fn) -> int:
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return counter.get_total_flops()


def measure(
    preset: str,
    agents: int,
    steps: int,
    peak: float,
    overrides: dict[str, Any] | None = None,
    device: str = "cpu",
) -> dict[str, float]:
    pop = population(preset, agents, overrides, device)
    c, dev = pop.config, pop.device
    pop.step()  # warm-up (and imagination memories filled)
    step_flops = flops_of(pop.step)
    step_s = timed(pop.step, steps, dev)
    gens = list(pop.generators)
    batch = pop.real.sample(c.model_batch * c.model_ensemble, gens)
    update_flops = flops_of(lambda: pop.model.update(batch, gens))
    update_s = timed(lambda: pop.model.update(batch, gens), max(steps, 5), dev)
    return {
        "steps_per_s": agents / step_s,
        "step_ms": 1000 * step_s,
        "m_update_ms": 1000 * update_s,
        "m_share": c.model_updates * update_s / step_s,
        "m_peak": update_flops / update_s / peak,
        "step_peak": step_flops / step_s / peak,
        "gflop_per_step": step_flops / 1e9 / agents,
    }


def greedy_seconds(episodes: int = 1000) -> tuple[float, float]:
    from imagine.envs.gesture_puzzle import make_composer
    from imagine.envs.gesture_puzzle.evaluation import greedy_success
    from imagine.models.controller import Controller
    from imagine.models.vision import ConvVAE

    class Encoder:  # V's cost, without a trained V run
        latent_dim = 8

        def __init__(self) -> None:
            self.vae = ConvVAE(latent_dim=8).eval()

        def encode(self, images, states):
            from imagine.models.vision import encode_images

            return encode_images(self.vae, images)

    torch.manual_seed(0)
    controller, encoder = Controller(8), Encoder()
    start = time.perf_counter()
    result = greedy_success(controller, encoder, "original", episodes, seed=0,
                            composer=make_composer())  # fmt: skip
    return time.perf_counter() - start, float(np.mean(result["mean_return"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--agents", default="1,5,20")
    parser.add_argument("--presets", default="fast,paper")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of every agent, e.g. model_ensemble=5")  # fmt: skip
    parser.add_argument("--compare", action="append", default=[], metavar="KEY=VALUE",
                        help="measure every row also with this on top, as a multiple")  # fmt: skip
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--dtypes", default="float32,bfloat16",
                        help="the products' dtypes to measure every row with")  # fmt: skip
    args = parser.parse_args()
    dtypes = args.dtypes.split(",")
    overrides = parse_assignments(args.set)
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    peaks = {name: peak_flops(device=device, dtype=getattr(torch, name)) for name in dtypes}
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        tf32 = peak_flops(device=device)
        torch.backends.cuda.matmul.allow_tf32 = False
        name = torch.cuda.get_device_name(device)
        rates = ", ".join(f"{k} {v / 1e12:.1f} TFLOP/s" for k, v in peaks.items())
        print(f"peak: {name}, 8192x8192 matmul: {rates}, TF32 {tf32 / 1e12:.1f} TFLOP/s "
              "(the % of peak below: of the row's dtype)")  # fmt: skip
    else:
        rates = ", ".join(f"{k} {v / 1e9:.1f} GFLOP/s" for k, v in peaks.items())
        print(f"peak: 2048x2048 matmul, {args.threads} thread(s): {rates}")
    if overrides:
        print("settings: " + ", ".join(f"{k}={v}" for k, v in overrides.items()))
    variants = [("reference", {})]
    if args.compare:
        variants.append(("+ " + ", ".join(args.compare), parse_assignments(args.compare)))
    extra = " settings | step / reference |" if args.compare else ""
    print(
        "| preset | agents | products | agent steps/s | ms per lockstep step | M update ms | "
        "M share of step | M at % of peak | step at % of peak | GFLOP per agent step |" + extra
    )
    print("|---|---|---|---|---|---|---|---|---|---|" + "---|---|" * bool(args.compare))
    for preset in args.presets.split(","):
        for agents in (int(a) for a in args.agents.split(",")):
            steps = args.steps if preset == "fast" else 2
            for dtype in dtypes:
                reference_ms = None
                for label, more in variants:
                    settings = {**overrides, **more, "matmul_dtype": dtype}
                    m = measure(preset, agents, steps, peaks[dtype], settings, args.device)
                    reference_ms = reference_ms or m["step_ms"]
                    cells = [preset, str(agents), dtype, f"{m['steps_per_s']:.1f}",
                             f"{m['step_ms']:.1f}", f"{m['m_update_ms']:.1f}",
                             f"{100 * m['m_share']:.0f}%", f"{100 * m['m_peak']:.0f}%",
                             f"{100 * m['step_peak']:.0f}%",
                             f"{m['gflop_per_step']:.2f}"]  # fmt: skip
                    if args.compare:
                        cells += [label, f"{m['step_ms'] / reference_ms:.2f}x"]
                    print("| " + " | ".join(cells) + " |", flush=True)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak memory of this process: {rss:.2f} GiB")
    if device.type == "cuda":
        gpu = torch.cuda.max_memory_allocated(device) / 2**30
        print(f"peak GPU memory allocated: {gpu:.2f} GiB")
    seconds, _ = greedy_seconds()
    print(f"1000 greedy test episodes through V, {args.threads} thread(s): {seconds:.2f} s")


if __name__ == "__main__":
    main()
