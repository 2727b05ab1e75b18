"""A stochastic human (issue 16): after each action the hand moves to another cube with
probability p. Does M's mixture learn the hand's probabilities, and what does that do to the
agents? Per p, four arms on one task, each a population of the same seeds, evaluated on the
same 1000 test episodes (with the same p) at every budget:

- ``baseline``: C on real transitions only;
- ``augmented``: the fast preset's augmented agent (imagination hands C M's most likely next
  state, so an imagined hand never moves);
- ``outcome``: the same with ``imagination_draw=outcome`` (a component drawn by its weight,
  then its mean: the hand moves as often as M's mixture says);
- ``one-component``: ``augmented`` with a one-component M (``n_components=1``), the control:
  a unimodal M has one next state per (state, action).

Trains ``OUT/p<p>/<arm>/seed-N`` through the budgets (two populations at a time, resumable;
what exists is skipped), then prints per p the success table (mean (std) and IQM [95%
bootstrap CI]) and, at each budget, M's accuracy and its calibration (``hand_calibration``:
the weight M's mixture puts on the hand kept, moved to either other cube or a wrong state, over
every transition from a non-terminal state, against the truth 1 - p, p/2, p/2; also drawn in
``OUT/calibration.png``)::

    .venv/bin/python scripts/stochastic_human.py runs/human --vae runs/vae-fast --ps 0.3,0.1 \\
        --seeds 0-4 --budgets 1000,2000 --arm-budgets baseline:1000,2000,4000
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from imagine.config import parse_seeds
from imagine.envs.gesture_puzzle.rules import best_success
from imagine.study.experiments import Job, LocalRunner
from imagine.study.report import iqm_interval

ARMS: dict[str, tuple[str, tuple[tuple[str, object], ...]]] = {
    "baseline": ("baseline", ()),
    "augmented": ("augmented", ()),
    "outcome": ("augmented", (("imagination_draw", "outcome"),)),
    "one-component": ("augmented", (("n_components", 1),)),
}


def human_jobs(out: Path, vae: Path, task: str, ps: list[float], arms: list[str],
               seeds: list[int], budgets: dict[str, list[int]]) -> list[Job]:  # fmt: skip
    """Every (p, arm, seed) job, p by p, arm by arm (populations run in this order), each
    evaluated at its arm's budgets."""
    return [
        Job(str(out / f"p{p}" / arm / f"seed-{s}"), task, ARMS[arm][0], s, tuple(budgets[arm]),
            vae_run=str(vae), overrides=(("hand_switch_prob", p), *ARMS[arm][1]))
        for p in ps for arm in arms for s in seeds
    ]  # fmt: skip


def read(job: Job, budget: int) -> dict | None:
    path = job.evaluation_path(budget)
    return json.loads(path.read_text()) if path.is_file() else None


def tables(jobs: list[Job], ps: list[float], arms: list[str], budgets: list[int]) -> str:
    """Per p: success by budget and arm; M's accuracy and calibration at each budget."""
    text = []
    for p in ps:
        mine = {arm: [j for j in jobs if dict(j.overrides)["hand_switch_prob"] == p
                      and Path(j.folder).parent.name == arm] for arm in arms}  # fmt: skip
        text += [f"### p = {p}", "", "| arm | " + " | ".join(
            f"{b}: mean (std) | {b}: IQM [95% CI]" for b in budgets) + " |",
            "| --- " * (1 + 2 * len(budgets)) + "|"]  # fmt: skip
        for arm in arms:
            cells = []
            for b in budgets:
                v = np.array([100 * e["success"] for j in mine[arm] if (e := read(j, b))])
                if len(v) == 0:
                    cells += ["-", "-"]
                    continue
                iqm, low, high = iqm_interval(v)
                std = f"{v.std(ddof=1):.1f}" if len(v) > 1 else "-"
                n = "" if len(v) == len(mine[arm]) else f", {len(v)} seeds"
                cells += [f"{v.mean():.1f} ({std}{n})", f"{iqm:.1f} [{low:.1f}, {high:.1f}]"]
            text.append(f"| {arm} | " + " | ".join(cells) + " |")
        best = 100 * best_success(jobs[0].task, p)[0]
        text.append("| best any policy can do (`rules.best_success`) | "
                    + " | ".join([f"{best:.1f}", ""] * len(budgets)) + " |")  # fmt: skip
        modelled = [j for arm in arms if ARMS[arm][0] == "augmented" for j in mine[arm]]
        shown = [b for b in budgets if any(read(j, b) for j in modelled)]
        text += ["", "M, mean over seeds: its most likely next state right (hand kept), a "
                 "sample right (arrows), samples that keep the hand "
                 f"(truth {1 - p:.2f}); the mixture's weight on each hand outcome (truth "
                 f"{1 - p:.2f} / {p / 2:.2f} / {p / 2:.2f} / 0) and its total variation from "
                 "the truth, from non-terminal states (what M learns from) and, from the "
                 "run's checkpoint where it is still at that budget, over all "
                 "192 x 6 transitions and on the (state, action) pairs of the agent's real "
                 "memory: M's TV and that of the frequencies counted there (these three over "
                 "the seeds whose checkpoint is at that budget; the counts read real images "
                 "through V's classifier, and few visits bias their TV upward).", "",
                 "| arm, episodes | most likely | sample | sample keeps hand | kept | "
                 "moved next | moved previous | wrong | TV | TV, all | pairs in M_R (median "
                 "visits) | M's TV there | counts' TV there |", "| --- " * 13 + "|"]  # fmt: skip
        text += [row for b in shown for arm in arms
                 if (row := model_row(f"{arm}, {b}", mine[arm], b))]  # fmt: skip
        text.append("")
    return "\n".join(text)


def model_row(label: str, jobs: list[Job], budget: int) -> str | None:
    """M's accuracy and calibration over the seeds of ``jobs`` at ``budget`` (None without M);
    from each run's checkpoint, where it is still at ``budget``: the calibration over all
    192 x 6 transitions, and on the (state, action) pairs of the agent's own real memory, M's
    total variation beside that of the counts of what followed them there (the tabular
    estimate from the same data)."""
    from imagine.envs.gesture_puzzle.evaluation import hand_calibration
    from imagine.learning.agent import load_agent

    evaluations = [e for j in jobs if (e := read(j, budget)) and e.get("model_accuracy")]
    if not evaluations:
        return None
    accuracy = [
        100 * np.mean([e["model_accuracy"][k] for e in evaluations])
        for k in ("transition_nonterminal", "transition_sampled", "hand_kept_sampled")
    ]
    calibration = [
        np.mean([e["hand_calibration"][k] for e in evaluations])
        for k in ("kept", "moved_next", "moved_previous", "wrong", "total_variation")
    ]
    everywhere, memory = [], []
    for job in jobs:
        saved = Path(job.folder) / "agent.json"
        if not read(job, budget) or json.loads(saved.read_text())["episode"] != budget:
            continue  # no checkpoint at this budget: trained on, or not yet there
        agent = load_agent(job.folder)
        if agent.episode == budget:
            p = agent.config.hand_switch_prob
            everywhere.append(
                hand_calibration(agent.model, agent.encoder, job.task, p, include_terminal=True)[
                    "total_variation"
                ]
            )
            memory.append(memory_calibration(job, agent, p))
    tv_all = f"{np.mean(everywhere):.3f}" if everywhere else "-"
    seen = (
        ("-",) * 3
        if not memory
        else (
            f"{np.mean([m[0] for m in memory]):.0f} ({np.mean([m[1] for m in memory]):.0f})",
            f"{np.mean([m[2] for m in memory]):.3f}",
            f"{np.mean([m[3] for m in memory]):.3f}",
        )
    )
    return (f"| {label} | " + " | ".join(f"{v:.1f}" for v in accuracy) + " | "
            + " | ".join(f"{v:.3f}" for v in calibration) + f" | {tv_all} | "
            + " | ".join(seen) + " |")  # fmt: skip


def memory_calibration(job: Job, agent, p: float) -> tuple[int, float, float, float]:
    """On the (state, action) pairs of the agent's real memory M_R (macrostates read by V's
    classifier): how many pairs, their median count, M's mean total variation from the truth
    there, and that of the pairs' empirical next-state frequencies."""
    from imagine.envs.gesture_puzzle.evaluation import (
        hand_outcome_weights,
        hand_total_variation,
        outcome_mass,
    )
    from imagine.envs.gesture_puzzle.rules import N_ACTIONS, apply_actions, macrostate_index
    from imagine.learning.agent_checkpoint import READABLE_FORMATS, read_checkpoint

    tensors, _ = read_checkpoint(Path(job.folder), READABLE_FORMATS)
    states = agent.encoder.classify(tensors["real.mu"]).numpy()
    following = agent.encoder.classify(tensors["real.next_mu"]).numpy()
    actions = tensors["real.action"].numpy()
    pair = macrostate_index(states) * N_ACTIONS + actions
    pairs, first, counts = np.unique(pair, return_index=True, return_counts=True)
    each = outcome_mass(
        apply_actions(states, actions), following[:, None, :], np.ones((len(states), 1))
    )  # one-hot outcome per transition
    sums = np.zeros((len(pairs), 4))
    np.add.at(sums, np.searchsorted(pairs, pair), each)
    counted = hand_total_variation(sums / counts[:, None], p).mean()
    modelled = hand_total_variation(
        hand_outcome_weights(agent.model, agent.encoder, states[first], actions[first]), p
    ).mean()
    return len(pairs), float(np.median(counts)), float(modelled), float(counted)


def calibration_png(jobs: list[Job], ps: list[float], arms: list[str], budget: int,
                    path: Path) -> None:  # fmt: skip
    """Per p, M's weight on each hand outcome by arm (mean over seeds, bars) against the
    truth (black ticks), at ``budget``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outcomes = ("kept", "moved_next", "moved_previous", "wrong")
    figure, axes = plt.subplots(1, len(ps), figsize=(5 * len(ps), 3.5), squeeze=False)
    for ax, p in zip(axes[0], ps, strict=True):
        truth = (1 - p, p / 2, p / 2, 0.0)
        shown = [a for a in arms if ARMS[a][0] == "augmented"]
        width = 0.8 / max(len(shown), 1)
        for n, arm in enumerate(shown):
            runs = [j for j in jobs if dict(j.overrides)["hand_switch_prob"] == p
                    and Path(j.folder).parent.name == arm]  # fmt: skip
            cal = [e["hand_calibration"] for j in runs if (e := read(j, budget))]
            if not cal:
                continue
            mean = [np.mean([c[k] for c in cal]) for k in outcomes]
            ax.bar(np.arange(4) + (n - (len(shown) - 1) / 2) * width, mean, width, label=arm)
        ax.scatter(np.arange(4), truth, marker="_", s=600, color="black", label="truth", zorder=3)
        ax.set_xticks(np.arange(4), ["hand kept", "moved next", "moved previous", "wrong"])
        ax.set_ylim(0, 1)
        ax.set_title(f"p = {p}: M's mixture weight, {budget} episodes")
        ax.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--vae", type=Path, required=True, help="V run (imagine vae train)")
    parser.add_argument("--task", default="hard")
    parser.add_argument("--ps", default="0.3,0.1")
    parser.add_argument("--arms", default=",".join(ARMS))
    parser.add_argument("--seeds", default="0-4")
    parser.add_argument("--budgets", default="1000,2000,4000")
    parser.add_argument(
        "--arm-budgets",
        action="append",
        default=[],
        metavar="ARM:BUDGETS",
        help="an arm's own budgets, e.g. baseline:1000,2000,4000 (repeatable)",
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--skip",
        default="",
        help="(p, arm) pairs not to train, e.g. "
        "0.1/outcome,0.1/one-component (their rows stay empty)",
    )
    parser.add_argument("--table-only", action="store_true", help="print what exists")
    args = parser.parse_args()
    ps = [float(p) for p in args.ps.split(",")]
    if not all(0.0 < p < 1.0 for p in ps):
        parser.error(f"--ps {args.ps}: each p must be in (0, 1): a stochastic human")
    arms = args.arms.split(",")
    if unknown := set(arms) - set(ARMS):
        parser.error(f"unknown arms {sorted(unknown)}; choose from {', '.join(ARMS)}")
    budgets = {arm: sorted(int(b) for b in args.budgets.split(",")) for arm in arms}
    for given in args.arm_budgets:
        arm, _, values = given.partition(":")
        if arm not in budgets:
            parser.error(f"--arm-budgets {given}: {arm!r} is not one of --arms")
        if not all(b.strip().isdigit() for b in values.split(",")):
            parser.error(f"--arm-budgets {given}: expected ARM:B1,B2,... (episode counts)")
        budgets[arm] = sorted(int(b) for b in values.split(","))
    jobs = human_jobs(args.out, args.vae, args.task, ps, arms, list(parse_seeds(args.seeds)),
                      budgets)  # fmt: skip
    skipped = set()
    for pair in filter(None, args.skip.split(",")):
        p, _, arm = pair.partition("/")
        if arm not in arms or float(p) not in ps:
            parser.error(f"--skip {pair}: expected P/ARM with P in --ps and ARM in --arms")
        skipped.add(f"p{float(p)}/{arm}")
    if not args.table_only:
        LocalRunner(args.workers).run(
            [j for j in jobs if not j.finished()
             and str(Path(j.folder).parent.relative_to(args.out)) not in skipped], lambda job: None,
            lambda job, error: print(f"{job.folder}: {error or 'done'}", flush=True),
        )  # fmt: skip
    print(tables(jobs, ps, arms, sorted({b for arm in arms for b in budgets[arm]})))
    last = max((b for arm in arms if ARMS[arm][0] == "augmented" for b in budgets[arm]),
               default=None)  # fmt: skip
    if last is not None:
        calibration_png(jobs, ps, arms, last, args.out / "calibration.png")
        print(f"figure: {args.out / 'calibration.png'}")


if __name__ == "__main__":
    main()
