"""Train and evaluate (task, method, seed) runs of the `fast` preset, two at a time, and print
mean (std) success per task and method. A stopgap until `imagine reproduce` (issue 5).

    .venv/bin/python scripts/fast_sweep.py --vae runs/vae-fast2 --out runs/sweep \\
        [--tasks original,hard] [--seeds 5] [--episodes 2000] [--workers 2] [--oracle]

Finished runs (with evaluation.json) are not run again.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

IMAGINE = str(Path(sys.executable).parent / "imagine")


def job(run: Path, task: str, method: str, seed: int, args: argparse.Namespace) -> None:
    if (run / "evaluation.json").is_file():
        return
    encoder = ["--oracle"] if args.oracle else ["--vae", args.vae]
    subprocess.run([IMAGINE, "train", str(run), "--task", task, "--method", method, "--seed",
                    str(seed), "--episodes", str(args.episodes), "--preset", "fast", *encoder],
                   check=True, capture_output=True)  # fmt: skip
    subprocess.run([IMAGINE, "evaluate", str(run)], check=True, capture_output=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", default="runs/vae-fast2")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"))
    parser.add_argument("--tasks", default="original,hard")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--oracle", action="store_true")
    args = parser.parse_args()
    jobs = [(args.out / f"{task}-{method}-{seed}", task, method, seed)
            for task in args.tasks.split(",") for seed in range(args.seeds)
            for method in ("baseline", "augmented")]  # fmt: skip
    with ThreadPoolExecutor(args.workers) as pool:
        for future in [pool.submit(job, *j, args) for j in jobs]:
            future.result()
    print(
        "| task | method | success % mean (std) | M accuracy %: all / non-terminal / sampled "
        "| runs |"
    )
    print("| --- | --- | --- | --- | --- |")
    for task in args.tasks.split(","):
        for method in ("baseline", "augmented"):
            found = [json.loads((run / "evaluation.json").read_text())
                     for run, t, m, _ in jobs if t == task and m == method
                     and (run / "evaluation.json").is_file()]  # fmt: skip
            success = 100 * np.array([r["success"] for r in found])
            accuracy = "-"
            if method == "augmented":
                keys = ("transition", "transition_nonterminal", "transition_sampled")
                means = [100 * np.mean([r["model_accuracy"][k] for r in found]) for k in keys]
                accuracy = " / ".join(f"{m:.1f}" for m in means)
            print(f"| {task} | {method} | {success.mean():.2f} ({success.std(ddof=1):.2f}) | "
                  f"{accuracy} | {len(found)} |")  # fmt: skip


if __name__ == "__main__":
    main()
