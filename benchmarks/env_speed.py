"""How fast GesturePuzzle makes images and steps, measured on this machine.

Prints images per second for batched synthesis (the VAE dataset's path), steps per second for
one environment and for the vectorized environment, and, as a reference measured in the same
run, the rate at which numpy merely gathers as many ready-made observations from a table.

    .venv/bin/python benchmarks/env_speed.py [--images 100000] [--num-envs 1000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from imagine.envs.gesture_puzzle import GesturePuzzleEnv, GesturePuzzleVectorEnv, make_composer
from imagine.envs.gesture_puzzle.dataset import DatasetConfig, synthesize
from imagine.envs.gesture_puzzle.rules import all_macrostates


def best_of(repeats: int, fn) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=100_000)
    parser.add_argument("--num-envs", type=int, default=1000)
    args = parser.parse_args()

    start = time.perf_counter()
    composer = make_composer()
    setup = time.perf_counter() - start

    n = args.images
    seconds = best_of(1, lambda: synthesize(DatasetConfig(n_train=n, n_test=1)))
    synth_rate = n / seconds

    rng = np.random.default_rng(0)
    states = all_macrostates()[rng.integers(0, 192, 8192)]
    frags = composer.pool.sample_indices(rng, states)
    # Reference: the least a synthesizer could do, one gather of a whole uint8 observation from
    # a table of ready-made ones (a table the size of the fragment parts).
    table = rng.integers(0, 256, (2048, 64, 64, 3), dtype=np.uint8)
    rows = rng.integers(0, len(table), 8192)
    copy_rate = 8192 / best_of(5, lambda: np.take(table, rows, axis=0))
    observe_rate = 8192 / best_of(5, lambda: composer.observe(states, frags))

    env = GesturePuzzleEnv()
    env.reset(seed=0)
    actions = rng.integers(0, 6, 10_000)

    def single():
        for a in actions:
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset()

    single_rate = len(actions) / best_of(1, single)

    venv = GesturePuzzleVectorEnv(args.num_envs)
    venv.reset(seed=0)
    batch = rng.integers(0, 6, (20, args.num_envs))

    def vector():
        for a in batch:
            venv.step(a)

    vector_rate = batch.size / best_of(3, vector)

    print(f"fragment pool + composer setup:        {setup:8.2f} s")
    print(f"dataset synthesis ({n:,} images):     {synth_rate:10,.0f} images/s")
    print(f"observe, batch of 8192:                {observe_rate:10,.0f} images/s")
    print(f"reference: gather of 8192 whole obs:   {copy_rate:10,.0f} images/s")
    print(f"  observe / gather ratio:              {observe_rate / copy_rate:10.3f}")
    print(f"single environment:                    {single_rate:10,.0f} steps/s")
    print(f"vector environment ({args.num_envs} envs):     {vector_rate:10,.0f} steps/s")
    print(f"  1000 episodes of 10 steps (vector):  {10 * 1000 / vector_rate:10.3f} s")


if __name__ == "__main__":
    main()
