"""Our agents beside Stable-Baselines3's DQN on any Gymnasium environment (``imagine compare``).

For each seed, the baseline and the augmented agent (Algorithm 1 with and without M, one
lockstep population per method) train to each step budget in turn (a run resumes to the next
budget), and Stable-Baselines3's DQN trains once to the largest budget with its RL Zoo
hyperparameters where the Zoo tunes the environment (its defaults otherwise), evaluated when it
passes each budget. Every agent is judged by the same greedy test episodes
(:func:`imagine.learning.test_episodes.run_episodes`, seed ``EVAL_SEED``): the table gives, per
method and budget, the mean return over seeds (std), and its interquartile mean with a 95% bootstrap
interval; the figure draws the IQM against steps with its interval.

SB3 is an optional extra (``pip install 'imagine[sb3]'``); without it the SB3 row is skipped with
a one-line message.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from imagine.checkpoint import (
    atomic_write_text,
    changed_fields,
    read_json,
    save_figure,
    with_defaults,
    write_json,
)
from imagine.config import AgentConfig, for_method
from imagine.envs.spec import gym_spec
from imagine.errors import ConfigError, NumericalError
from imagine.learning.extras import extras_of
from imagine.learning.test_episodes import EpsilonGreedy, agent_policy, run_episodes
from imagine.study.provenance import commit, provenance
from imagine.study.report import iqm_interval

EVAL_SEED = 1_000_000
METHODS = ("baseline", "control", "augmented", "sb3-dqn")
"""Every arm a comparison can hold, in table order: the paper's baseline, the replay-ratio
control (the baseline with the augmented agent's C and as many C updates per real step,
:func:`control_overrides`), the augmented agent, SB3's DQN."""


def control_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """The replay-ratio control's settings over a baseline's: from I_start on, C makes the
    augmented agent's N_I extra updates per real step on real batches
    (``real_in_place_of_imagined``), and with it the augmented agent's target network
    (:data:`imagine.config.CONTROL_FROM_AUGMENTED`), so that the two differ only in where
    their extra batches come from."""
    return {**values, "method": "baseline", "real_in_place_of_imagined": True}


def arm_settings(values: dict[str, Any], arm: str) -> dict[str, Any]:
    """The AgentConfig fields of one of our arms (``baseline``, ``control``, ``augmented``)
    over the settings ``values`` given to all of them (:func:`imagine.config.for_method`)."""
    method = "augmented" if arm == "augmented" else "baseline"
    mine = for_method(values, method) | {"method": method}
    return control_overrides(mine) if arm == "control" else mine


SB3_ZOO: dict[str, dict[str, Any]] = {
    "CartPole-v1": {
        "learning_rate": 2.3e-3, "batch_size": 64, "buffer_size": 100_000,
        "learning_starts": 1000, "gamma": 0.99, "target_update_interval": 10,
        "train_freq": 256, "gradient_steps": 128, "exploration_fraction": 0.16,
        "exploration_final_eps": 0.04, "policy_kwargs": {"net_arch": [256, 256]},
    },
    "Acrobot-v1": {
        "learning_rate": 6.3e-4, "batch_size": 128, "buffer_size": 50_000,
        "learning_starts": 0, "gamma": 0.99, "target_update_interval": 250,
        "train_freq": 4, "gradient_steps": -1, "exploration_fraction": 0.12,
        "exploration_final_eps": 0.1, "policy_kwargs": {"net_arch": [256, 256]},
    },
}  # fmt: skip
"""RL Zoo's tuned DQN settings (rl-baselines3-zoo, hyperparams/dqn.yml) for the environments
compared in docs/any-environment.md and the suite (``imagine bench``); the Zoo tunes CartPole-v1
for 5e4 steps and Acrobot-v1 for 1e5, and the exploration schedule here keeps that horizon
(``SB3_ZOO_STEPS``) whatever the budgets."""
SB3_ZOO_STEPS = {"CartPole-v1": 50_000, "Acrobot-v1": 100_000}


NUDGE = 0.001
"""The epsilon of the second test of every agent (:class:`EpsilonGreedy`): a greedy result
that falls apart at one random action in a thousand is a policy circling, not one that
fails."""


def judged(spec, make_policy: Callable[[], Any], episodes: int) -> dict[str, Any]:
    """The greedy test episodes of a policy (``make_policy()``: a fresh one), and the same
    episodes with a random action at probability :data:`NUDGE` a step (``nudged_*``)."""
    greedy = run_episodes(spec, make_policy(), episodes, EVAL_SEED)
    nudged = run_episodes(spec, EpsilonGreedy(make_policy(), spec.n_actions, NUDGE, EVAL_SEED),
                          episodes, EVAL_SEED)  # fmt: skip
    return {**greedy, "nudge_epsilon": NUDGE, "nudged_mean_return": nudged["mean_return"],
            "nudged_truncated": nudged["truncated"]}  # fmt: skip


def check_evaluation(path: Path, config: AgentConfig, episodes: int) -> None:
    """A one-line error if the evaluation at ``path`` was made by another config or on
    another number of test episodes than those asked for now (a result is reused only for
    what it measured)."""
    saved = read_json(path, "evaluation")
    asked = json.loads(json.dumps(dataclasses.asdict(config)))  # tuples as JSON lists
    changed = changed_fields(with_defaults(AgentConfig, saved.get("config", asked)), asked)
    if saved.get("episodes") != episodes:
        changed = ", ".join(filter(None, [changed, f"test episodes {saved.get('episodes')} -> "
                                                   f"{episodes}"]))  # fmt: skip
    if changed:
        raise ConfigError(f"{path} was made with another setting ({changed}): give another "
                          "OUT or remove that arm's folder")  # fmt: skip


def evaluation_path(folder: Path, steps: int) -> Path:
    return folder / f"evaluation-{steps:07d}.json"


def train_ours(
    config: AgentConfig,
    out: Path,
    seeds: Sequence[int],
    budgets: Sequence[int],
    episodes: int,
    log: Callable[[str], None] = print,
    arm: str | None = None,
) -> None:
    """One arm's seeds (default: the config's method), to each budget in turn, each evaluated
    there (resumable); every evaluation records its config, the commit and V's hash."""
    from imagine.learning.training import train_population

    arm = arm or config.method
    spec = gym_spec(config.env, tuple(config.wrappers))
    folders = [out / arm / f"seed-{s}" for s in seeds]
    for budget in sorted(budgets):
        todo = [i for i, f in enumerate(folders) if not evaluation_path(f, budget).is_file()]
        for i in set(range(len(folders))) - set(todo):
            asked = dataclasses.replace(config, seed=seeds[i], steps=budget)
            check_evaluation(evaluation_path(folders[i], budget), asked, episodes)
        if not todo:
            continue
        configs = [dataclasses.replace(config, seed=seeds[i], steps=budget) for i in todo]
        log(f"{arm}: seeds {[seeds[i] for i in todo]} to {budget} steps")
        result = train_population(configs, [folders[i] for i in todo], threads=1)
        for i, agent in zip(todo, result.agents, strict=True):
            if agent is None:
                raise NumericalError(result.failures[todo.index(i)])
            evaluation = judged(spec, partial(agent_policy, agent, episodes), episodes)
            write_json(evaluation_path(folders[i], budget),
                       {"method": arm, "seed": seeds[i], "steps": budget, **evaluation,
                        **probed(agent), **provenance(configs[todo.index(i)])})  # fmt: skip


def probed(agent) -> dict[str, Any]:
    """``{"model_probe": {key: accuracy}}``: the environment's probe of the agent's learned M
    on held-out real transitions (:class:`~imagine.learning.extras.EnvExtras`), where it has M
    and the environment a probe; else nothing. An accuracy with nothing to measure (NaN: no
    terminal transition among Acrobot-v1's) is null."""
    probe = extras_of(agent.config.env).model_probe
    if probe is None or not agent.config.trains_model:
        return {}
    readings = probe(agent.model, agent.encoder, agent.config)
    return {"model_probe": {k: None if np.isnan(v) else v for k, v in readings.items()}}


def sb3_available() -> bool:
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return False
    return True


def without_log_folder(model: Any) -> Any:
    """``model`` (an SB3 algorithm) logging nowhere: by default every ``learn`` makes a folder
    ``SB3-<date>`` in the system's temporary directory, never removed."""
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def train_sb3(
    env_id: str,
    wrappers: Sequence[str],
    out: Path,
    seeds: Sequence[int],
    budgets: Sequence[int],
    episodes: int,
    log: Callable[[str], None] = print,
    horizon: int | None = None,
) -> None:
    """SB3's DQN per seed to the largest budget, evaluated as it passes each budget. Its
    exploration schedule and default buffer follow ``horizon`` (default: the largest budget;
    at least the Zoo's steps where the Zoo tunes the environment), so a partial run's first
    budgets are those of the whole run. A run extended to more budgets trains from step 0
    again (deterministic per seed, so it repeats the budgets it had)."""
    from stable_baselines3 import DQN

    from imagine.envs.gym import make_env

    spec = gym_spec(env_id, tuple(wrappers))
    horizon = max(horizon or max(budgets), max(budgets), SB3_ZOO_STEPS.get(env_id, 0))
    # SB3's defaults otherwise, but a replay buffer no larger than the run (its default of 1e6
    # images would take 9 GB for 56 x 56 RGB observations)
    settings = SB3_ZOO.get(env_id, {"buffer_size": min(1_000_000, horizon)})
    for seed in seeds:
        folder = out / "sb3-dqn" / f"seed-{seed}"
        todo = sorted(b for b in budgets if not evaluation_path(folder, b).is_file())
        if not todo:
            continue
        log(f"sb3-dqn: seed {seed} to {max(todo)} steps")
        policy_name = "CnnPolicy" if spec.kind == "image" else "MlpPolicy"
        model = without_log_folder(DQN(policy_name, make_env(env_id, wrappers), seed=seed,
                                       device="cpu", verbose=0, **settings))  # fmt: skip
        # the exploration schedule of the Zoo's horizon; learning stops at the largest budget
        evaluate = sb3_evaluations(spec, folder, seed, todo, episodes, settings)
        model.learn(total_timesteps=horizon, callback=evaluate)


def sb3_evaluations(spec, folder: Path, seed: int, budgets: list[int], episodes: int,
                    settings: dict[str, Any]):  # fmt: skip
    """An SB3 callback: at each budget, SB3's greedy policy through the same test episodes;
    stops learning after the largest."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            steps = self.num_timesteps
            if steps in budgets:
                model = self.model

                def greedy():
                    return lambda x, extra, copies: model.predict(x, deterministic=True)[0]

                evaluation = judged(spec, greedy, episodes)
                write_json(evaluation_path(folder, steps),
                           {"method": "sb3-dqn", "seed": seed, "steps": steps,
                            "rl_zoo": spec.env_id in SB3_ZOO, "settings": settings,
                            "commit": commit(), **evaluation})  # fmt: skip
            return steps < max(budgets)

    return Evaluate()


def gather(out: Path) -> list[dict[str, Any]]:
    """Every evaluation under ``out`` (method/seed-N/evaluation-*.json)."""
    return [read_json(p, "evaluation") for p in sorted(out.glob("*/seed-*/evaluation-*.json"))]


def summarize(evaluations: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (method, steps): n, mean return (std), IQM [95% bootstrap interval]."""
    groups: dict[tuple[str, int], list[float]] = {}
    extra: dict[tuple[str, int], dict[str, list[float]]] = {}
    for e in evaluations:
        key = (e["method"], int(e["steps"]))
        groups.setdefault(key, []).append(e["mean_return"])
        for name in ("truncated", "nudged_mean_return"):
            if name in e:
                extra.setdefault(key, {}).setdefault(name, []).append(e[name])
    rows = []
    order = {m: i for i, m in enumerate(METHODS)}
    for (method, steps), values in sorted(groups.items(),
                                          key=lambda kv: (kv[0][1], order[kv[0][0]])):  # fmt: skip
        x = np.asarray(values)
        iqm, low, high = iqm_interval(x)
        more = {name: float(np.mean(v)) for name, v in extra.get((method, steps), {}).items()
                if len(v) == len(x)}  # fmt: skip
        rows.append({"method": method, "steps": steps, "n": len(x), "mean": float(x.mean()),
                     "std": float(x.std(ddof=1)) if len(x) > 1 else 0.0, "iqm": iqm,
                     "iqm_low": low, "iqm_high": high, **more})  # fmt: skip
    return rows


def markdown_table(env_id: str, rows: list[dict[str, Any]]) -> str:
    lines = [f"Greedy mean return on {env_id} (per seed: mean of the test episodes). "
             "Time-limited: the share of greedy episodes ended by the time limit; at "
             f"epsilon {NUDGE}: the mean return of the same episodes with a random action at "
             "that probability a step (means over seeds).", "",
             "| steps | method | seeds | mean (std) | IQM [95% CI] | time-limited | "
             f"mean at epsilon {NUDGE} |",
             "|---:|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        cut = f"{100 * r['truncated']:.0f}%" if "truncated" in r else "-"
        nudged = f"{r['nudged_mean_return']:.1f}" if "nudged_mean_return" in r else "-"
        lines.append(f"| {r['steps']} | {r['method']} | {r['n']} | {r['mean']:.1f} "
                     f"({r['std']:.1f}) | {r['iqm']:.1f} [{r['iqm_low']:.1f}, "
                     f"{r['iqm_high']:.1f}] | {cut} | {nudged} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def figure(env_id: str, rows: list[dict[str, Any]], path: Path) -> Path:
    """IQM of the mean return against steps, with its 95% interval, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for method in METHODS:
        mine = [r for r in rows if r["method"] == method]
        if not mine:
            continue
        steps = [r["steps"] for r in mine]
        ax.plot(steps, [r["iqm"] for r in mine], marker="o", label=method)
        ax.fill_between(steps, [r["iqm_low"] for r in mine], [r["iqm_high"] for r in mine],
                        alpha=0.2)  # fmt: skip
    ax.set_xlabel("environment steps")
    ax.set_ylabel("greedy mean return (IQM, 95% CI)")
    ax.set_title(env_id)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def report(env_id: str, out: Path, seeds: Sequence[int] | None = None) -> tuple[str, Path]:
    """The table (also OUT/comparison.md and .json) and the figure (OUT/comparison.png), of
    the evaluations under OUT (of ``seeds`` only, if given)."""
    rows = summarize([e for e in gather(out) if seeds is None or e["seed"] in seeds])
    table = markdown_table(env_id, rows)
    atomic_write_text(out / "comparison.md", table)
    write_json(out / "comparison.json", rows)
    return table, figure(env_id, rows, out / "comparison.png")
