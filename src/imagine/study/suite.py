"""The sample-efficiency suite (``imagine bench SUITE OUT``; issue 57).

A suite file (``suites/*.yaml``) names environments, each with its step budgets, the preset
its agents start from, its own settings (such as I_start) and a reference score. Every arm
trains on every environment and seed to each budget and is judged by the same greedy test
episodes (:mod:`imagine.study.compare`):

- ``baseline``: the paper's baseline, one C update per real step;
- ``control``: the replay-ratio control, the baseline with the augmented agent's C (its
  target network included) and as many C updates per real step as the augmented agent makes,
  real and imagined together (:func:`imagine.study.compare.control_overrides`);
- ``augmented``: Algorithm 1 with M and imaginary rollouts;
- ``sb3-dqn``: Stable-Baselines3's DQN, RL Zoo settings where the Zoo tunes the environment.

OUT holds one folder per environment (its runs, ``comparison.md``, ``.json`` and ``.png``) and
``SUITE.md``: the tables, each environment's score normalised by a random policy (0) and the
reference (1), and the verdicts the issue asks of imagination: where it hurts (its IQM
interval wholly below the stronger baseline's) and where it pays (wholly above both).
Everything is resumable: a finished evaluation is never trained again.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from imagine.checkpoint import atomic_write_text, read_json, write_json
from imagine.config import (
    PRESETS,
    AgentConfig,
    agent_preset,
    load_yaml,
    parse_seeds,
)
from imagine.errors import ConfigError, ImagineError
from imagine.study.compare import (
    EVAL_SEED,
    METHODS,
    arm_settings,
    gather,
    report,
    sb3_available,
    train_ours,
    train_sb3,
)
from imagine.study.report import iqm_interval

ARMS = METHODS
"""The suite's arms, in table order."""

MIN_SEEDS = 3
"""Fewer seeds than this and the suite claims nothing (its intervals are too wide to read)."""

BASELINES = ("baseline", "control")
"""The two baselines imagination must beat: the stronger of them at each budget is the bar."""


@dataclasses.dataclass(frozen=True)
class SuiteEnv:
    """One environment of a suite and every choice made for it."""

    env: str
    """What ``gymnasium.make`` takes (``module:Id`` imports the module that registers it)."""
    budgets: tuple[int, ...]
    """Real environment steps at which every arm is evaluated."""
    reference: float
    """A published score (normalised score 1), e.g. the RL Zoo DQN's."""
    reference_source: str
    """Where ``reference`` comes from."""
    wrappers: tuple[str, ...] = ()
    """Gymnasium wrappers ``module:Class``, applied in order."""
    preset: str = "fast"
    """The preset our three arms start from."""
    settings: tuple[tuple[str, Any], ...] = ()
    """AgentConfig fields over the preset (``set:`` in the file), for every arm of ours."""
    vae: str | None = None
    """V's run folder for image observations (``imagine vae train --env ...``)."""

    @property
    def slug(self) -> str:
        """The environment's folder name under OUT."""
        return re.sub(r"[^A-Za-z0-9._-]+", "-", self.env).strip("-")


@dataclasses.dataclass(frozen=True)
class Suite:
    environments: tuple[SuiteEnv, ...]
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    episodes: int = 100
    """Greedy test episodes per agent and budget."""
    arms: tuple[str, ...] = ARMS


def load_suite(path: str | Path) -> Suite:
    """A suite file, every key checked (a one-line :class:`ConfigError` naming the bad one)."""
    raw = load_yaml(path)
    known = {"seeds", "episodes", "arms", "environments"}
    for key in raw:
        if key not in known:
            raise ConfigError(f"{path}: unknown key {key!r} (a suite has {sorted(known)})")
    entries = raw.get("environments")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: 'environments' must be a non-empty list")
    arms = raw.get("arms", list(ARMS))
    if (not isinstance(arms, list) or not arms
            or any(not isinstance(a, str) or a not in ARMS for a in arms)):  # fmt: skip
        raise ConfigError(f"{path}: arms is a list of {', '.join(ARMS)}; got {arms!r}")
    episodes = raw.get("episodes", 100)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"{path}: episodes must be a positive integer, got {episodes!r}")
    seeds = raw.get("seeds", "0-4")
    if isinstance(seeds, list) and all(isinstance(x, int) and not isinstance(x, bool)
                                       for x in seeds):  # fmt: skip
        seeds = ",".join(map(str, seeds))
    if isinstance(seeds, bool) or not isinstance(seeds, str | int):
        raise ConfigError(f"{path}: seeds is e.g. 0-4 or [0, 1, 2], got {seeds!r}")
    try:
        chosen = parse_seeds(str(seeds))
    except ConfigError:
        raise ConfigError(f"{path}: seeds is e.g. 0-4 or [0, 1, 2], got {seeds!r}") from None
    environments = tuple(_suite_env(path, i, e) for i, e in enumerate(entries))
    slugs = [e.slug for e in environments]
    if len(set(slugs)) < len(slugs):
        twice = sorted({e.env for e in environments if slugs.count(e.slug) > 1})
        raise ConfigError(f"{path}: environments {twice} would share one folder: name each once")
    return Suite(environments, chosen, episodes, tuple(a for a in ARMS if a in arms))


def _suite_env(path: str | Path, index: int, entry: Any) -> SuiteEnv:
    where = f"{path}: environments[{index}]"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where} must be a mapping")
    known = {"env", "budgets", "reference", "reference_source", "wrappers", "preset", "set",
             "vae"}  # fmt: skip
    for key in entry:
        if key not in known:
            raise ConfigError(f"{where}: unknown key {key!r} (an environment has {sorted(known)})")
    for key in ("env", "budgets", "reference", "reference_source"):
        if key not in entry:
            raise ConfigError(f"{where} needs {key!r}")
    budgets = entry["budgets"]
    if (not isinstance(budgets, list) or not budgets
            or any(not isinstance(b, int) or b < 1 for b in budgets)):  # fmt: skip
        raise ConfigError(f"{where}: budgets must be a list of positive step counts")
    preset = entry.get("preset", "fast")
    if preset not in PRESETS:
        raise ConfigError(f"{where}: preset is one of {', '.join(PRESETS)}, got {preset!r}")
    settings = entry.get("set", {}) or {}
    if not isinstance(settings, dict):
        raise ConfigError(f"{where}: 'set' must be a mapping of AgentConfig fields")
    reference = entry["reference"]
    if isinstance(reference, bool) or not isinstance(reference, int | float):
        raise ConfigError(f"{where}: reference must be a number, got {reference!r}")
    return SuiteEnv(str(entry["env"]), tuple(sorted(set(budgets))), float(reference),
                    str(entry["reference_source"]), tuple(entry.get("wrappers", []) or []),
                    preset, tuple(sorted(settings.items())), entry.get("vae"))  # fmt: skip


def arm_config(entry: SuiteEnv, arm: str) -> AgentConfig:
    """The resolved AgentConfig of one of our arms on ``entry`` (seed 0, its first budget):
    the preset's settings for the arm's method, then the suite's."""
    from imagine.learning.agent import UNBOUNDED_EPISODES, with_encoder_of_env

    values: dict[str, Any] = {**dict(entry.settings), "env": entry.env,
                              "wrappers": list(entry.wrappers),
                              "episodes": UNBOUNDED_EPISODES}  # fmt: skip
    if entry.vae is not None:
        values["vae_run"] = entry.vae
    values = with_encoder_of_env(values)
    return agent_preset(entry.preset, **arm_settings(values, arm), steps=entry.budgets[0])


def check_suite(suite: Suite) -> None:
    """Every arm's config of every environment resolves (errors before any training)."""
    for entry in suite.environments:
        for arm in suite.arms:
            if arm != "sb3-dqn":
                arm_config(entry, arm)


def run_suite(
    suite: Suite,
    out: Path,
    envs: Sequence[str] | None = None,
    arms: Sequence[str] | None = None,
    workers: int = 1,
    log: Callable[[str], None] = print,
    up_to: int | None = None,
) -> Path:
    """Train what is missing of every (environment, arm) asked for (all by default), each
    cell one population of the suite's seeds on one thread, ``workers`` cells at once; with
    ``up_to``, only the budgets up to that many steps (a partial run a later one extends);
    then write every environment's table and figure and OUT/SUITE.md; returns its path."""
    out.mkdir(parents=True, exist_ok=True)
    cells = []
    for entry in suite.environments:
        if envs is not None and entry.env not in envs:
            continue
        budgets = tuple(b for b in entry.budgets if up_to is None or b <= up_to)
        if not budgets:
            continue
        (out / entry.slug).mkdir(exist_ok=True)
        random_score(entry, out / entry.slug, suite.episodes)
        for arm in suite.arms:
            if arms is not None and arm not in arms:
                continue
            if arm == "sb3-dqn" and not sb3_available():
                log("sb3-dqn skipped: stable-baselines3 is not installed "
                    "(pip install 'imagine[sb3]')")  # fmt: skip
                continue
            cells.append((entry, arm, budgets))
    if workers <= 1 or len(cells) <= 1:
        for entry, arm, budgets in cells:
            run_cell(suite, entry, arm, budgets, out, log)
    else:
        _run_cells(suite, cells, out, workers, log)
    return write_suite_report(suite, out)


def run_cell(
    suite: Suite,
    entry: SuiteEnv,
    arm: str,
    budgets: Sequence[int],
    out: Path,
    log: Callable[[str], None] = print,
) -> None:
    """One arm's seeds on one environment, to each of ``budgets`` (resumable), holding the
    arm's folder lock: two ``imagine bench`` processes never train the same cell."""
    import torch

    from imagine.study.experiments import folder_lock

    torch.set_num_threads(1)
    folder = out / entry.slug
    prefixed = lambda line: log(f"{entry.env} {line}")  # noqa: E731
    with folder_lock(folder / arm):
        if arm == "sb3-dqn":
            train_sb3(entry.env, list(entry.wrappers), folder, suite.seeds, budgets,
                      suite.episodes, log=prefixed, horizon=max(entry.budgets))  # fmt: skip
        else:
            train_ours(arm_config(entry, arm), folder, suite.seeds, budgets, suite.episodes,
                       log=prefixed, arm=arm)  # fmt: skip


def _run_cells(suite, cells, out: Path, workers: int, log: Callable[[str], None]) -> None:
    """The cells in ``workers`` spawned processes; a cell that fails is named, the others
    go on, and the error is raised once all have stopped."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    failures = []
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        futures = {pool.submit(run_cell, suite, entry, arm, budgets, out): (entry.env, arm)
                   for entry, arm, budgets in cells}  # fmt: skip
        for future in as_completed(futures):
            env, arm = futures[future]
            try:
                future.result()
                log(f"{env} {arm}: done")
            except Exception as exc:  # reported here, raised once all have stopped
                failures.append(f"{env} {arm}: {exc}")
                log(f"{env} {arm} failed: {exc}")
    if failures:
        raise ImagineError("; ".join(failures))


def random_score(entry: SuiteEnv, folder: Path, episodes: int) -> float:
    """The mean return of uniform random actions over the suite's test episodes (normalised
    score 0), measured once and kept in ``random.json``."""
    path = folder / "random.json"
    if path.is_file():
        return float(read_json(path, "random policy")["mean_return"])
    from imagine.envs.spec import gym_spec
    from imagine.learning.test_episodes import random_policy, run_episodes

    spec = gym_spec(entry.env, entry.wrappers)
    result = run_episodes(spec, random_policy(spec.n_actions, 0), episodes, EVAL_SEED)
    write_json(path, {"env": entry.env, **result})
    return float(result["mean_return"])


def normalised(value: float, random: float, reference: float) -> float:
    """A score on the scale random policy = 0, reference = 1 (NaN if the two are equal)."""
    return (value - random) / (reference - random) if reference != random else float("nan")


def verdicts(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per budget, imagination against the stronger baseline (the one of higher IQM among
    :data:`BASELINES`): ``hurts`` when the augmented agent's IQM interval lies wholly below
    its interval, ``pays`` when it lies wholly above both baselines' intervals; ``judged``
    only with at least :data:`MIN_SEEDS` seeds in every row compared."""
    out = []
    for steps in sorted({r["steps"] for r in rows}):
        at = {r["method"]: r for r in rows if r["steps"] == steps}
        ours, bars = at.get("augmented"), [at[b] for b in BASELINES if b in at]
        if ours is None or not bars:
            continue
        strongest = max(bars, key=lambda r: r["iqm"])
        seeds = min(r["n"] for r in (ours, *bars))
        out.append({"steps": steps, "stronger": strongest["method"], "seeds": seeds,
                    "judged": seeds >= MIN_SEEDS,
                    "hurts": ours["iqm_high"] < strongest["iqm_low"],
                    "pays": len(bars) == len(BASELINES)
                            and all(ours["iqm_low"] > b["iqm_high"] for b in bars),
                    "complete": len(bars) == len(BASELINES)})  # fmt: skip
    return out


def verdict_text(verdict: dict[str, Any], key: str) -> str:
    """``yes`` or ``no`` for a verdict's ``hurts`` or ``pays``; no claim from too few seeds."""
    if not verdict["judged"]:
        return f"no claim ({verdict['seeds']} seeds)"
    return "yes" if verdict[key] else "no"


def steps_to_match(rows: list[dict[str, Any]]) -> tuple[int | None, int | None]:
    """The largest budget both baselines have reached, with at least :data:`MIN_SEEDS` seeds
    in every row read, and the fewest steps at which the augmented agent's mean reaches the
    stronger baseline's mean there (by IQM, as :func:`verdicts` picks it); None where there is
    no such budget, or the augmented agent does not reach it."""
    judged = [r for r in rows if r["n"] >= MIN_SEEDS]
    reached = [{r["steps"] for r in judged if r["method"] == b} for b in BASELINES]
    common = set.intersection(*reached)
    if not common:
        return None, None
    last = max(common)
    bar = max((r for r in judged if r["steps"] == last and r["method"] in BASELINES),
              key=lambda r: r["iqm"])["mean"]  # fmt: skip
    ours = sorted((r["steps"], r["mean"]) for r in judged if r["method"] == "augmented")
    return last, next((steps for steps, mean in ours if mean >= bar), None)


def normalised_rows(entry: SuiteEnv, evaluations: list[dict[str, Any]], random: float):
    """Per arm at the environment's largest budget that every arm evaluated so far has
    reached: n, normalised IQM [95% CI] over seeds."""
    reached: dict[str, set[int]] = {}
    for e in evaluations:
        reached.setdefault(e["method"], set()).add(int(e["steps"]))
    common = set.intersection(*reached.values()) if reached else set()
    last = max(common) if common else max(entry.budgets)
    rows = []
    for arm in ARMS:
        values = [normalised(e["mean_return"], random, entry.reference) for e in evaluations
                  if e["method"] == arm and int(e["steps"]) == last]  # fmt: skip
        if values:
            iqm, low, high = iqm_interval(np.asarray(values))
            rows.append({"arm": arm, "steps": last, "n": len(values), "iqm": iqm,
                         "low": low, "high": high})  # fmt: skip
    return rows


PROBE_KEYS = ("next_state", "terminal", "nonterminal", "reward")
"""What the vector environments' probe of M reads (:func:`imagine.envs.classic_control.extras.
model_probe`), in the report's column order."""


def probe_rows(env: str, evaluations: list[dict[str, Any]]) -> list[str]:
    """One table row per budget where augmented evaluations carry M's probe: each accuracy's
    mean over those seeds (``-`` where none measured it)."""
    by_steps: dict[int, list[dict[str, Any]]] = {}
    for e in evaluations:
        if e.get("method") == "augmented" and e.get("model_probe"):
            by_steps.setdefault(e["steps"], []).append(e["model_probe"])
    rows = []
    for steps, probes in sorted(by_steps.items()):
        cells = []
        for key in PROBE_KEYS:
            values = [p[key] for p in probes if p.get(key) is not None]
            cells.append(f"{100 * np.mean(values):.1f}%" if values else "-")
        rows.append(f"| {env} | {steps} | {len(probes)} | " + " | ".join(cells) + " |")
    return rows


def write_suite_report(suite: Suite, out: Path) -> Path:
    """Every environment's table and figure (``comparison.*`` in its folder) and OUT/SUITE.md."""
    lines = ["# The sample-efficiency suite", "",
             f"Seeds {', '.join(map(str, suite.seeds))}; {suite.episodes} greedy test episodes "
             "per agent and budget (the same for every arm). IQM with a 95% bootstrap "
             "interval over seeds.", ""]  # fmt: skip
    summary = ["## Normalised score at each environment's largest budget", "",
               "(The largest that every arm has reached, in a partial run.)", "",
               "0: a uniform random policy on the same test episodes; 1: the reference.", "",
               "| environment | reference | random | arm | seeds | normalised IQM [95% CI] |",
               "| --- | ---: | ---: | --- | ---: | ---: |"]  # fmt: skip
    judged = ["## Imagination against the stronger baseline", "",
              "`hurts`: the augmented agent's IQM interval lies wholly below the stronger "
              "baseline's; `pays`: wholly above both baselines'. Steps to match: the fewest "
              "steps at which the augmented mean reaches the stronger baseline's mean at the "
              "largest budget both baselines reached.", "",
              "| environment | steps | stronger baseline | hurts | pays |",
              "| --- | ---: | --- | --- | --- |"]  # fmt: skip
    probed = ["## M on held-out real transitions", "",
              "The augmented agent's M at each budget on 2000 transitions of a random policy "
              "(means over seeds): next state within a tenth of the true step; d right on the "
              "terminal transitions and on the others; r within 0.5.", "",
              "| environment | steps | seeds | next state | d, terminal | d, nonterminal | r |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    matched = []
    for entry in suite.environments:
        folder = out / entry.slug
        if not folder.is_dir() or not gather(folder):
            continue
        table, _ = report(entry.env, folder, suite.seeds)
        lines += [f"## {entry.env}", "", table, f"![{entry.env}]({entry.slug}/comparison.png)",
                  ""]  # fmt: skip
        random = random_score(entry, folder, suite.episodes)
        mine = [e for e in gather(folder) if e["seed"] in suite.seeds]
        probed += probe_rows(entry.env, mine)
        for r in normalised_rows(entry, mine, random):
            summary.append(f"| {entry.env} | {entry.reference:g} ({entry.reference_source}) | "
                           f"{random:.1f} | {r['arm']} | {r['n']} | {r['iqm']:.2f} "
                           f"[{r['low']:.2f}, {r['high']:.2f}] |")  # fmt: skip
        rows = read_json(folder / "comparison.json", "comparison")
        for v in verdicts(rows):
            note = "" if v["complete"] else " (one baseline missing)"
            hurts, pays = (verdict_text(v, k) for k in ("hurts", "pays"))
            judged.append(f"| {entry.env} | {v['steps']} | {v['stronger']}{note} | {hurts} | "
                          f"{pays} |")  # fmt: skip
        last, match = steps_to_match(rows)
        if last is None:
            matched.append(f"- {entry.env}: no budget that both baselines reached with "
                           f"{MIN_SEEDS} seeds or more")  # fmt: skip
        else:
            reached = "not reached" if match is None else f"{match} steps"
            matched.append(f"- {entry.env}: {reached} (the stronger baseline at {last})")
    seeds = len(suite.seeds)
    caveat = ([] if seeds >= MIN_SEEDS else
              [f"With {seeds} seed(s) the intervals say nothing: no claim is made from them.",
               ""])  # fmt: skip
    path = out / "SUITE.md"
    probe = [*probed, ""] if len(probed) > 6 else []
    atomic_write_text(path, "\n".join([*lines, *caveat, *summary, "", *judged, "",
                                       "Steps to match:", *matched, "", *probe]))  # fmt: skip
    return path
