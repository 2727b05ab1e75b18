"""Reward transfer (issue 16): episodes to 90% greedy success on `hard` for agents whose M
starts from `original` agents' MDNs (``--init-from``), against `hard` agents from scratch.

The sources are the augmented `original` agents of a finished study (``STUDY/runs/
original-augmented-N``, seed N for seed N); the from-scratch arm is the same study's augmented
`hard` agents, evaluated on the same 1000 test episodes (seed 1,000,000) at the same budgets,
with the same V. Trains ``OUT/seed-N`` budget by budget (each a resume of the last) and
evaluates each seed at each budget (``OUT/seed-N/evaluation-B.json``), skipping what exists,
then prints the table (mean (std) and IQM [95% bootstrap CI] per budget and arm, and the
episodes at which the mean curve first reaches 90%)::

    .venv/bin/python scripts/reward_transfer.py results runs/transfer-hard --seeds 0-4 \\
        --budgets 250,500,1000,1500,2000 --sources runs/transfer-src
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from imagine.config import parse_seeds
from imagine.study.report import first_reaching, iqm_interval

IMAGINE = str(Path(sys.executable).parent / "imagine")


def run_transfer(study: Path, out: Path, sources: Path, seeds: list[int],
                 budgets: list[int]) -> None:  # fmt: skip
    """Train and evaluate what is missing; ``sources/seed-N`` links to the study's run N."""
    sources.mkdir(parents=True, exist_ok=True)
    for s in seeds:
        link = sources / f"seed-{s}"
        if not link.exists():
            link.symlink_to((study / "runs" / f"original-augmented-{s}").resolve())
    for b in budgets:
        if all((out / f"seed-{s}" / f"evaluation-{b}.json").is_file() for s in seeds):
            continue
        subprocess.run([IMAGINE, "train", str(out), "--task", "hard", "--method", "augmented",
                        "--seeds", ",".join(map(str, seeds)), "--episodes", str(b),
                        "--vae", str(study / "vae"), "--init-from", str(sources)],
                       check=True)  # fmt: skip
        for s in seeds:
            run = out / f"seed-{s}"
            subprocess.run([IMAGINE, "evaluate", str(run)], check=True, capture_output=True)
            shutil.copyfile(run / "evaluation.json", run / f"evaluation-{b}.json")


def success(path: Path) -> float:
    return 100 * json.loads(path.read_text())["success"]


def table(study: Path, out: Path, seeds: list[int], budgets: list[int]) -> str:
    scratch = study / "runs"
    arms = {
        "from scratch": [[success(scratch / f"hard-augmented-{s}" / f"evaluation-{b:05d}.json")
                          for b in budgets] for s in seeds],
        "M from original": [[success(out / f"seed-{s}" / f"evaluation-{b}.json") for b in budgets]
                            for s in seeds],
    }  # fmt: skip
    names = list(arms)
    x = {arm: np.array(curves) for arm, curves in arms.items()}
    lines = ["| hard, augmented: episodes | " + " | ".join(
                 f"{arm}: mean (std) | IQM [95% CI]" for arm in names) + " |",
             "| --- " * (1 + 2 * len(names)) + "|"]  # fmt: skip
    for j, b in enumerate(budgets):
        cells = []
        for arm in names:
            v = x[arm][:, j]
            iqm, low, high = iqm_interval(v)
            cells += [f"{v.mean():.1f} ({v.std(ddof=1):.1f})", f"{iqm:.1f} [{low:.1f}, {high:.1f}]"]
        lines.append(f"| {b} | " + " | ".join(cells) + " |")
    firsts = [first_reaching(budgets, list(x[arm].mean(0)), 90.0) for arm in names]
    lines.append("| episodes to 90% (mean curve) | " + " | ".join(
        f"{f or f'> {budgets[-1]}'} | " for f in firsts) + "|")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--sources", type=Path, help="folder of seed-N links (default OUT-sources)")
    parser.add_argument("--seeds", default="0-4")
    parser.add_argument("--budgets", default="250,500,1000,1500,2000")
    args = parser.parse_args()
    seeds = list(parse_seeds(args.seeds))
    budgets = [int(b) for b in args.budgets.split(",")]
    sources = args.sources or args.out.with_name(args.out.name + "-sources")
    run_transfer(args.study, args.out, sources, seeds, budgets)
    print(table(args.study, args.out, seeds, budgets))


if __name__ == "__main__":
    main()
