"""The study's tables, figures and REPORT.md (paper section V, Tables I and II, Fig. 4).

Statistics: per (task, method, budget) the mean (std) success over seeds, as the paper reports,
and beside it the interquartile mean (IQM) with a 95% percentile-bootstrap confidence interval,
the protocol of rliable (Agarwal et al. 2021). With one task per table the stratified bootstrap
has a single stratum, so ``scipy.stats.bootstrap`` over ``scipy.stats.trim_mean(x, 0.25)`` gives
the same statistic without rliable's pandas<3 pin and ~300 MB of dependencies.
"""

from __future__ import annotations

import csv
import io
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from imagine.checkpoint import atomic_write_text, save_figure

METHODS = ("baseline", "augmented")
PEER = "sb3-dqn"
"""A peer baseline's method name (:mod:`imagine.study.peer`): a column where a study has it."""

PAPER_TABLES: dict[str, dict[int, tuple[float, float, float, float]]] = {
    # budget: (baseline mean, std, augmented mean, std), success % (paper Tables I and II)
    "original": {2000: (42.18, 6.01, 57.34, 6.37), 3000: (62.88, 4.91, 81.4, 2.95),
                 4000: (81.44, 3.13, 91.88, 2.38), 5000: (88.22, 3.07, 95.1, 3.76),
                 6000: (92.16, 2.57, 96.96, 2.1)},
    "hard": {2000: (30.12, 4.16, 53.78, 3.16), 3000: (49.56, 8.48, 75.1, 3.5),
             4000: (62.54, 2.92, 81.12, 5.35), 5000: (79.44, 2.97, 94.88, 1.8),
             6000: (84.66, 2.73, 95.03, 2.23)},
}  # fmt: skip
PAPER_RANDOM = {"original": 3.72, "hard": 3.39}


def iqm_interval(values: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """Interquartile mean and its 95% percentile-bootstrap interval (2000 resamples)."""
    values = np.asarray(values, dtype=float)
    iqm = float(stats.trim_mean(values, 0.25))
    if len(values) < 2 or np.ptp(values) == 0:
        return iqm, iqm, iqm
    result = stats.bootstrap(
        (values,), lambda x, axis: stats.trim_mean(x, 0.25, axis=axis), n_resamples=2000,
        confidence_level=0.95, method="percentile", random_state=seed,
    )  # fmt: skip
    interval = result.confidence_interval
    return iqm, float(interval.low), float(interval.high)


def summarize(evaluations: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (task, budget, method): n, mean, std (ddof 1), IQM and its interval, in %."""
    groups: dict[tuple[str, int, str], list[float]] = defaultdict(list)
    on_mu: dict[tuple[str, int, str], list[float]] = defaultdict(list)
    for e in evaluations:
        key = (e["task"], int(e["budget"]), e["method"])
        groups[key].append(100 * e["success"])
        on_mu[key].append(100 * e.get("success_observation", math.nan))
    rows = []
    order = {"original": 0, "hard": 1}
    method_order = {m: i for i, m in enumerate(METHODS)}
    for (task, budget, method), values in sorted(
        groups.items(), key=lambda kv: (order.get(kv[0][0], 2), kv[0][0], kv[0][1],
                                        method_order.get(kv[0][2], 2)),
    ):  # fmt: skip
        x, mu = np.array(values), np.array(on_mu[(task, budget, method)])
        iqm, low, high = iqm_interval(x)
        paper = PAPER_TABLES.get(task, {}).get(budget) if method in METHODS else None
        offset = 0 if method == "baseline" else 2
        rows.append({
            "task": task, "budget": budget, "method": method, "n": len(x),
            "mean": float(x.mean()), "std": float(x.std(ddof=1)) if len(x) > 1 else 0.0,
            "iqm": iqm, "iqm_low": low, "iqm_high": high,
            "paper_mean": paper[offset] if paper else math.nan,
            "paper_std": paper[offset + 1] if paper else math.nan,
            # an agent acting on a belief (belief: filtered) is also tested on V's means alone
            "observation_mean": float(mu.mean()),
            "observation_std": float(mu.std(ddof=1)) if len(mu) > 1 else 0.0,
        })  # fmt: skip
    return rows


def increase(base: float, augmented: float) -> float:
    """The paper's % increase of augmented over baseline."""
    return 100 * (augmented - base) / base if base > 0 else math.nan


def markdown_table(task: str, rows: list[dict[str, Any]], random_success: float) -> str:
    """Table I (original) or II (hard): ours beside the paper's."""
    cell = {(r["budget"], r["method"]): r for r in rows if r["task"] == task}
    budgets = sorted({b for b, _ in cell})
    peer = any(m == PEER for _, m in cell)  # SB3's DQN, when the study has it
    # augmented agents acting on a belief, each also tested on V's means alone
    on_mu = any(m == "augmented" and not math.isnan(r["observation_mean"])
                for (_, m), r in cell.items())  # fmt: skip
    lines = [
        "| Episodes | Base DQN | Augmented | % increase | IQM base [95% CI] | "
        "IQM augmented [95% CI] | paper base | paper augmented | paper % increase |"
        + (" Augmented on V's means |" if on_mu else "")
        + (" SB3 DQN | IQM SB3 DQN [95% CI] |" if peer else ""),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"
        + (" --- |" if on_mu else "")
        + (" --- | --- |" if peer else ""),
    ]
    for budget in budgets:
        base, aug = cell.get((budget, "baseline")), cell.get((budget, "augmented"))
        ours = [f"{r['mean']:.2f} ({r['std']:.2f})" if r else "-" for r in (base, aug)]
        gain = f"{increase(base['mean'], aug['mean']):.2f}" if base and aug else "-"
        iqms = [f"{r['iqm']:.2f} [{r['iqm_low']:.2f}, {r['iqm_high']:.2f}]" if r else "-"
                for r in (base, aug)]  # fmt: skip
        paper = PAPER_TABLES.get(task, {}).get(budget)
        theirs = ["-", "-", "-"]
        if paper:
            theirs = [f"{paper[0]:.2f} ({paper[1]:.2f})", f"{paper[2]:.2f} ({paper[3]:.2f})",
                      f"{increase(paper[0], paper[2]):.2f}"]  # fmt: skip
        more = []
        if on_mu:
            more.append(f"{aug['observation_mean']:.2f} ({aug['observation_std']:.2f})"
                        if aug and not math.isnan(aug["observation_mean"]) else "-")  # fmt: skip
        if peer:
            r = cell.get((budget, PEER))
            more += ([f"{r['mean']:.2f} ({r['std']:.2f})",
                      f"{r['iqm']:.2f} [{r['iqm_low']:.2f}, {r['iqm_high']:.2f}]"]
                     if r else ["-", "-"])  # fmt: skip
        lines.append(f"| {budget} | {' | '.join([*ours, gain, *iqms, *theirs, *more])} |")
    lines.append(
        f"| random agent | {100 * random_success:.2f} | | | | | "
        f"{PAPER_RANDOM.get(task, math.nan):.2f} | | |"
        + (" |" if on_mu else "")
        + (" | |" if peer else "")
    )
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: f"{v:.4f}" if isinstance(v, float) else v for k, v in row.items()})
    return buffer.getvalue()


def write_tables(out: Path, rows: list[dict[str, Any]], random: dict[str, float]) -> dict[str, str]:
    """tables/table_<task>.md and .csv for each task; returns the Markdown per task."""
    folder = out / "tables"
    folder.mkdir(parents=True, exist_ok=True)
    tables = {}
    for task in dict.fromkeys(r["task"] for r in rows):
        tables[task] = markdown_table(task, rows, random[task])
        atomic_write_text(folder / f"table_{task}.md", tables[task])
        task_rows = [r for r in rows if r["task"] == task]
        atomic_write_text(folder / f"table_{task}.csv", csv_text(task_rows))
    return tables


MIN_SEEDS = 3
"""The fewest seeds per (task, method, budget) that REPORT.md draws a claim from."""


def too_few_seeds(rows: list[dict[str, Any]]) -> int | None:
    """The seeds per (task, method, budget) of ``rows`` (the fewest) when they are fewer than
    :data:`MIN_SEEDS`, else None."""
    seeds = min((r["n"] for r in rows if r["method"] in METHODS), default=0)
    return seeds if seeds < MIN_SEEDS else None


def claims(rows: list[dict[str, Any]]) -> list[str]:
    """What our numbers say about the paper's claims, one sentence each, from the rows; from
    fewer than :data:`MIN_SEEDS` seeds, one line that says none is made."""
    seeds = too_few_seeds(rows)
    if seeds is not None:
        return [
            f"- **No claims**: {seeds} seed{'s' if seeds != 1 else ''} per (task, method, "
            f"budget) cannot tell the methods apart, nor ours from the paper's; claims need at "
            f"least {MIN_SEEDS} seeds (e.g. `--seeds 0-{MIN_SEEDS - 1}`)."
        ]
    cell = {(r["task"], r["budget"], r["method"]): r for r in rows}
    lines = []
    for task in dict.fromkeys(r["task"] for r in rows):
        budgets = sorted({r["budget"] for r in rows if r["task"] == task})
        wins = [b for b in budgets if (task, b, "baseline") in cell and (task, b, "augmented")
                in cell and cell[(task, b, "augmented")]["mean"] > cell[(task, b, "baseline")]
                ["mean"]]  # fmt: skip
        separated = [b for b in wins if cell[(task, b, "augmented")]["iqm_low"]
                     > cell[(task, b, "baseline")]["iqm_high"]]  # fmt: skip
        verdict = "supported" if len(wins) == len(budgets) else (
            "partly supported" if wins else "not supported")  # fmt: skip
        lines.append(
            f"- **{task}: augmented beats baseline** ({verdict} by our numbers): higher mean at "
            f"{len(wins)} of {len(budgets)} budgets ({', '.join(map(str, wins)) or 'none'}); "
            f"IQM intervals apart at {', '.join(map(str, separated)) or 'none'}."
        )
        paper = PAPER_TABLES.get(task, {})
        compared = [b for b in budgets if b in paper and (task, b, "augmented") in cell]
        if not compared:
            lines.append(f"- **{task}: against the paper's augmented agent**: the paper has no "
                         "numbers at these budgets.")  # fmt: skip
            continue
        at_least = [b for b in compared if cell[(task, b, "augmented")]["mean"] >= paper[b][2]]
        lines.append(
            f"- **{task}: our augmented agent at least as good as the paper's**: at "
            f"{len(at_least)} of {len(compared)} budgets "
            f"({', '.join(map(str, at_least)) or 'none'})."
        )
    return lines


def area_under_curve(budgets: list[int], success: list[float]) -> float:
    """Mean success over the span of the budgets: the trapezoid area under the success curve
    divided by the span (so 100 means 100% at every budget)."""
    if len(budgets) < 2:
        return float(success[0])
    x, y = np.asarray(budgets, dtype=float), np.asarray(success, dtype=float)
    area = float(((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2).sum())
    return area / (x[-1] - x[0])


def first_reaching(budgets: list[int], success: list[float], level: float) -> int | None:
    """The first budget at which ``success`` reaches ``level`` (None if it never does)."""
    return next((b for b, x in zip(budgets, success, strict=True) if x >= level), None)


def curve_summary(evaluations: list[dict[str, Any]], level: float = 90.0) -> list[dict[str, Any]]:
    """One row per (task, method) over the learning curve of every seed: the area under the
    success curve (mean and IQM with its 95% bootstrap interval over seeds), the episodes at
    which the mean curve first reaches ``level`` % and the median over seeds of each seed's own."""
    runs: dict[tuple[str, str], dict[int, dict[int, float]]] = defaultdict(dict)
    for e in evaluations:
        runs[(e["task"], e["method"])].setdefault(e["seed"], {})[int(e["budget"])] = (
            100 * e["success"]
        )
    order = {"original": 0, "hard": 1}
    out = []
    for (task, method), seeds in sorted(runs.items(), key=lambda kv: (
            order.get(kv[0][0], 2), kv[0][0], METHODS.index(kv[0][1]) if kv[0][1] in METHODS
            else 2)):  # fmt: skip
        budgets = sorted(set.intersection(*(set(c) for c in seeds.values())))
        curves = np.array([[c[b] for b in budgets] for c in seeds.values()])
        areas = np.array([area_under_curve(budgets, list(c)) for c in curves])
        iqm, low, high = iqm_interval(areas)
        own = [first_reaching(budgets, list(c), level) for c in curves]
        reached = sorted(b for b in own if b is not None)
        out.append({
            "task": task, "method": method, "n": len(curves), "budgets": budgets,
            "auc_mean": float(areas.mean()), "auc_iqm": iqm, "auc_low": low, "auc_high": high,
            "episodes_to_level": first_reaching(budgets, list(curves.mean(0)), level),
            "median_seed_episodes_to_level": (
                float(np.median(reached)) if len(reached) * 2 > len(own) else None
            ),
            "seeds_reaching_level": len(reached), "level": level,
        })  # fmt: skip
    return out


def curve_table(summary: list[dict[str, Any]]) -> str:
    """The learning-curve summary as Markdown."""
    lines = [
        "| task | method | seeds | area under the success curve, mean | IQM [95% CI] | "
        "episodes to 90% (mean curve) | episodes to 90% (median seed) | seeds reaching 90% |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in summary:
        first = r["episodes_to_level"] or f"> {r['budgets'][-1]}"
        median = r["median_seed_episodes_to_level"]
        median = f"{median:.0f}" if median is not None else f"> {r['budgets'][-1]}"
        lines.append(
            f"| {r['task']} | {r['method']} | {r['n']} | {r['auc_mean']:.2f} | "
            f"{r['auc_iqm']:.2f} [{r['auc_low']:.2f}, {r['auc_high']:.2f}] | {first} | "
            f"{median} | {r['seeds_reaching_level']} of {r['n']} |"
        )
    return "\n".join(lines) + "\n"


def where_paper_stood(rows: list[dict[str, Any]], budget: int = 2000) -> list[str]:
    """For each task: the first budget at which our baseline's mean reaches the paper's
    baseline mean at ``budget`` episodes; nothing from fewer than :data:`MIN_SEEDS` seeds."""
    if too_few_seeds(rows) is not None:
        return []
    lines = []
    for task in dict.fromkeys(r["task"] for r in rows):
        paper = PAPER_TABLES.get(task, {}).get(budget)
        ours = sorted((r["budget"], r["mean"]) for r in rows
                      if r["task"] == task and r["method"] == "baseline")  # fmt: skip
        if paper is None or not ours:
            continue
        at = first_reaching([b for b, _ in ours], [m for _, m in ours], paper[0])
        where = f"by {at} episodes" if at is not None else "at none of our budgets"
        lines.append(
            f"- **{task}: where the paper's baseline stood at {budget} episodes** "
            f"({paper[0]:.1f}%): our baseline's mean reaches it {where} (first budget "
            f"{ours[0][0]}: {ours[0][1]:.1f}%)."
        )
    return lines


def success_figure(rows: list[dict[str, Any]], out: Path) -> Path:
    """Success % against training episodes per task (paper Fig. 4 left): each method's IQM
    over seeds with its 95% bootstrap interval as a band and its mean as dots; the paper's
    mean (std) dashed."""
    from matplotlib.figure import Figure

    tasks = sorted({r["task"] for r in rows})
    fig = Figure(figsize=(5.5 * len(tasks), 4), layout="constrained")
    for i, task in enumerate(tasks):
        ax = fig.add_subplot(1, len(tasks), i + 1)
        for method, color in zip((*METHODS, PEER), ("tab:blue", "tab:red", "tab:green"),
                                 strict=True):  # fmt: skip
            mine = sorted((r["budget"], r["mean"], r["iqm"], r["iqm_low"], r["iqm_high"])
                          for r in rows if r["task"] == task and r["method"] == method)  # fmt: skip
            if mine:
                b, m, iqm, low, high = zip(*mine, strict=True)
                ax.plot(b, iqm, color=color, label=f"{method}, IQM and 95% CI")
                ax.fill_between(b, low, high, color=color, alpha=0.2)
                ax.plot(b, m, color=color, ls="none", marker="o", ms=3, label=f"{method}, mean")
            paper = PAPER_TABLES.get(task, {}) if method in METHODS else {}
            if paper:
                k = 0 if method == "baseline" else 2
                pb = sorted(paper)
                ax.errorbar(pb, [paper[b][k] for b in pb], yerr=[paper[b][k + 1] for b in pb],
                            color=color, ls="--", alpha=0.5, capsize=3,
                            label=f"{method} (paper)")  # fmt: skip
        ax.set(title=f"{task} task", xlabel="training episodes", ylabel="success % (greedy)",
               ylim=(0, 100))  # fmt: skip
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, out)


def increase_figure(rows: list[dict[str, Any]], out: Path) -> Path:
    """% increase of augmented over baseline against episodes, both tasks (paper Fig. 4 right)."""
    from matplotlib.figure import Figure

    cell = {(r["task"], r["budget"], r["method"]): r["mean"] for r in rows}
    fig = Figure(figsize=(5.5, 4), layout="constrained")
    ax = fig.add_subplot()
    for task, color in zip(sorted({r["task"] for r in rows}), ("tab:green", "tab:purple"),
                           strict=False):  # fmt: skip
        budgets = sorted(b for t, b, m in cell if t == task and m == "augmented"
                         and (t, b, "baseline") in cell)  # fmt: skip
        gains = [increase(cell[(task, b, "baseline")], cell[(task, b, "augmented")])
                 for b in budgets]  # fmt: skip
        ax.plot(budgets, gains, marker="o", color=color, label=task)
        paper = PAPER_TABLES.get(task, {})
        if paper:
            pb = sorted(paper)
            ax.plot(pb, [increase(paper[b][0], paper[b][2]) for b in pb], ls="--", alpha=0.5,
                    color=color, label=f"{task} (paper)")  # fmt: skip
    ax.axhline(0, color="k", lw=0.8)
    ax.set(xlabel="training episodes", ylabel="% increase of augmented over baseline")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, out)


def accuracy_figure(run_folders: list[Path], out: Path) -> Path | None:
    """M's accuracy over training episodes (mean over the augmented runs): all 192 x 6
    transitions, non-terminal ones, sampled, and r and d."""
    from matplotlib.figure import Figure

    from imagine.metrics import read_metrics

    keys = ("transition", "transition_nonterminal", "transition_sampled", "reward", "terminal")
    curves: dict[tuple[str, str], dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for folder in run_folders:
        task = folder.name.split("-")[0]
        if not (folder / "metrics.csv").is_file():
            continue
        for row in read_metrics(folder / "metrics.csv"):
            for key in keys:
                if f"model/{key}_accuracy" in row:
                    curves[(task, key)][int(row["step"])].append(row[f"model/{key}_accuracy"])
    if not curves:
        return None
    tasks = sorted({t for t, _ in curves})
    fig = Figure(figsize=(5.5 * len(tasks), 4), layout="constrained")
    for i, task in enumerate(tasks):
        ax = fig.add_subplot(1, len(tasks), i + 1)
        for key in keys:
            points = sorted(curves.get((task, key), {}).items())
            if points:
                ax.plot([p[0] for p in points], [100 * np.mean(p[1]) for p in points],
                        marker=".", label=key)  # fmt: skip
        ax.set(title=f"M accuracy, {task} task (augmented runs)", xlabel="training episodes",
               ylabel="% right", ylim=(0, 100))  # fmt: skip
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, out)


def m_studies(evaluations: list[dict[str, Any]]) -> list[str]:
    """REPORT.md lines on plans and generalization, per task, from the augmented agents."""
    lines = []
    for task in dict.fromkeys(e["task"] for e in evaluations):
        plans = [e for e in evaluations if e["task"] == task and "plans" in e]
        if plans:
            trials = sum(e["plans"]["trials"] for e in plans)
            ok = sum(e["plans"]["successes"] for e in plans)
            optimal = sum(e["plans"]["optimal"] for e in plans)
            per_seed = ", ".join(f"{e['plans']['successes']}/{e['plans']['trials']}"
                                 for e in sorted(plans, key=lambda e: e["seed"]))  # fmt: skip
            lines.append(
                f"- **{task}, plans** (augmented agents at {plans[0]['budget']} episodes, 20 "
                f"plans each): {ok} of {trials} succeeded ({100 * ok / trials:.0f}%), "
                f"{optimal} optimal ({100 * optimal / max(ok, 1):.0f}% of successes); per seed "
                f"{per_seed}. Paper (robot, original task): 17 of 20, every success optimal."
            )
        tests = [e for e in evaluations if e["task"] == task and "generalization" in e]
        if tests:
            trial = np.array([100 * e["generalization"]["trial_accuracy"] for e in tests])
            every = np.array([100 * e["generalization"]["all_terminal_accuracy"] for e in tests])
            std = trial.std(ddof=1) if len(trial) > 1 else 0.0
            lines.append(
                f"- **{task}, model generalization** (augmented agents at {tests[0]['budget']} "
                f"episodes): M's next state from terminal states right in {trial.mean():.1f}% "
                f"({std:.1f}) of 20 random trials, {every.mean():.1f}% over all "
                f"{tests[0]['generalization']['all_terminal_transitions']} terminal "
                f"transitions{first_member(tests)}. Paper: 75% of 20 trials after 5000 "
                "episodes."
            )
    return lines


def first_member(tests: list[dict]) -> str:
    """With an ensemble of Ms (whose prediction is the members' mean mode): the first
    member's share over all terminal transitions alone."""
    key = "all_terminal_accuracy_first_member"
    if not all(key in e["generalization"] for e in tests):
        return ""
    alone = np.mean([100 * e["generalization"][key] for e in tests])
    return f" (M's ensemble: the members' mean mode; its first member alone {alone:.1f}%)"
