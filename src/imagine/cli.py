"""The `imagine` command. A thin layer over the library: every subcommand parses its options,
calls one function, and turns a user error (:class:`~imagine.errors.ImagineError`) into a
one-line message and exit status 2."""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from imagine import ENV_ID
from imagine.errors import ImagineError


def _flags_show_no_type() -> None:
    """A flag takes no value, so its help shows none: typer 0.29 with click 8.2+ prints
    ``<bool>`` beside every flag (``--help`` included); a flag's type is left out here."""
    option = getattr(getattr(typer, "core", None), "TyperOption", None)
    shown = getattr(option, "display_type_rich", None)
    if shown is None or getattr(shown, "flags_show_no_type", False):
        return

    def display_type_rich(self, ctx):
        return None if getattr(self, "is_flag", False) else shown(self, ctx)

    display_type_rich.flags_show_no_type = True
    option.display_type_rich = display_type_rich
    argument = getattr(typer.core, "TyperArgument", None)
    shown_argument = getattr(argument, "display_type_rich", None)
    if shown_argument is not None:  # an argument with a metavar: the metavar says it all

        def argument_type_rich(self, ctx):
            return None if getattr(self, "metavar", None) else shown_argument(self, ctx)

        argument.display_type_rich = argument_type_rich


_flags_show_no_type()
app = typer.Typer(
    help="Deep RL with imaginary rollouts (Thabet et al. 2019): V, M and C on GesturePuzzle.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode="markdown",  # a docstring's lines join into sentences; `code` shows as code
)
env_app = typer.Typer(
    help="The GesturePuzzle environment.", no_args_is_help=True, rich_markup_mode="markdown"
)
app.add_typer(env_app, name="env")
vae_app = typer.Typer(
    help="V: the beta-VAE that encodes scenes into latent states.",
    no_args_is_help=True,
    rich_markup_mode="markdown",
)
app.add_typer(vae_app, name="vae")
console = Console(stderr=True)


def duration(seconds: float) -> str:
    """``1:02:03`` or ``2:03``: hours, minutes and seconds."""
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


class Bar:
    """Progress in ``unit`` (episodes, steps, runs) with what :meth:`update` says of it (the
    recent return or success): a rich bar on a terminal; in a log file, where a bar shows
    nothing until the end, a plain line every ``every`` of the total (done/total, unit,
    elapsed time and ETA)."""

    def __init__(self, label: str, total: int, unit: str, done: int = 0, every: float = 0.05):
        self.label, self.total, self.unit, self.every = label, max(int(total), 1), unit, every
        self.done = self.first = int(done)
        self.info = ""
        self.terminal = console.is_terminal
        self.start = time.perf_counter()
        self.printed = -1
        self.progress: Progress | None = None

    def __enter__(self) -> Bar:
        if self.terminal:
            self.progress = Progress(
                TextColumn(escape(self.label)), BarColumn(), MofNCompleteColumn(),
                TextColumn(self.unit), TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
                TextColumn("ETA"), TimeRemainingColumn(), console=console,
            )  # fmt: skip
            self.progress.__enter__()
            self.task = self.progress.add_task(self.unit, total=self.total,
                                               completed=self.done, info="")  # fmt: skip
        return self

    def update(self, done: int, info: str | None = None) -> None:
        self.done = min(int(done), self.total)
        self.info = self.info if info is None else info
        if self.progress is not None:
            self.progress.update(self.task, completed=self.done, info=self.info)
            return
        step = int(self.done / self.total / self.every)
        if step > self.printed:
            self.printed = step
            self._line()

    def _line(self) -> None:
        elapsed = time.perf_counter() - self.start
        gained = self.done - self.first
        eta = duration(elapsed * (self.total - self.done) / gained) if gained > 0 else "?"
        info = f", {self.info}" if self.info else ""
        line = (
            f"{self.label}: {self.done}/{self.total} {self.unit} "
            f"({100 * self.done / self.total:.0f}%){info}, {duration(elapsed)} elapsed, ETA {eta}"
        )
        console.print(line, markup=False, highlight=False, soft_wrap=True)

    def __exit__(self, *exc) -> None:
        if self.progress is not None:
            self.progress.__exit__(*exc)


class TaskName(StrEnum):
    original = "original"
    hard = "hard"


FragmentsOption = Annotated[
    Path | None,
    typer.Option(help="Folder of fragment photographs (docs/guide.md); default: procedural."),
]
FragmentSeedOption = Annotated[int, typer.Option(min=0, help="Seed of the procedural renderer.")]
CubeFragmentsOption = Annotated[
    int, typer.Option(help="Procedural fragments per (cube, direction) microstate.")
]
WrapperOption = Annotated[
    list[str] | None,
    typer.Option(metavar="MODULE:CLASS", help="A Gymnasium wrapper for --env (repeat: in order)."),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        metavar="KEY=VALUE",
        help="An agent config field over the preset (VALUE read as YAML); repeatable.",
    ),
]
HandFragmentsOption = Annotated[int, typer.Option(help="Procedural fragments per pointed cube.")]
VisionSetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set", metavar="KEY=VALUE", help="A V config field over the preset (VALUE read as YAML)."
    ),
]


@env_app.command("show")
def env_show(
    task: Annotated[
        TaskName, typer.Option(help="Which goal: original or hard.")
    ] = TaskName.original,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the examples drawn.")] = 0,
    out: Annotated[Path, typer.Option(help="PNG to write.")] = Path("results/contact_sheet.png"),
    fragments: FragmentsOption = None,
    fragment_seed: FragmentSeedOption = 0,
    n_cube_fragments: CubeFragmentsOption = 16,
    n_hand_fragments: HandFragmentsOption = 50,
) -> None:
    """Write a PNG contact sheet of the task's scenes.

    Example scenes of goal, illegal and start states with their labels and observations, and
    the fragment variation of one microstate."""
    from imagine.envs.gesture_puzzle import make_composer
    from imagine.envs.gesture_puzzle.contact_sheet import contact_sheet

    composer = make_composer(fragments, fragment_seed, n_cube_fragments, n_hand_fragments)
    path = contact_sheet(composer, task.value, seed, out)
    console.print(f"wrote {path}")


@env_app.command("export-fragments")
def env_export_fragments(
    folder: Annotated[Path, typer.Argument(help="Folder to write the fragment PNGs into.")],
    fragment_seed: FragmentSeedOption = 0,
    n_cube_fragments: CubeFragmentsOption = 16,
    n_hand_fragments: HandFragmentsOption = 50,
) -> None:
    """Write the procedural fragments as a folder, a template for your own.

    The folder has the layout `--fragments` reads: replace its images by fragments cut from
    your own camera."""
    from imagine.envs.gesture_puzzle import procedural_pool, save_fragment_folder

    pool = procedural_pool(fragment_seed, n_cube_fragments, n_hand_fragments)
    console.print(f"wrote {save_fragment_folder(pool, folder)}")


@app.command("dataset")
def dataset(
    out: Annotated[Path, typer.Argument(help="safetensors file to write.")],
    n_train: Annotated[int, typer.Option(help="Training images.")] = 100_000,
    n_test: Annotated[int, typer.Option(help="Test images.")] = 10_000,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the states and fragments drawn.")] = 0,
    fragments: FragmentsOption = None,
    fragment_seed: FragmentSeedOption = 0,
    n_cube_fragments: CubeFragmentsOption = 16,
    n_hand_fragments: HandFragmentsOption = 50,
) -> None:
    """Synthesize the images V trains on (the paper's 100,000 training and 10,000 test)."""
    from imagine.envs.gesture_puzzle import make_composer
    from imagine.envs.gesture_puzzle.dataset import DatasetConfig, save_dataset, synthesize

    make_composer(fragments, fragment_seed, n_cube_fragments, n_hand_fragments)  # check first
    config = DatasetConfig(
        n_train,
        n_test,
        seed,
        None if fragments is None else str(fragments),
        fragment_seed,
        n_cube_fragments,
        n_hand_fragments,
    )
    start = time.perf_counter()
    with Progress(
        TextColumn("synthesizing"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
    ) as bar:
        task_id = bar.add_task("images", total=n_train + n_test)
        arrays = synthesize(config, progress=lambda n: bar.advance(task_id, n))
    seconds = time.perf_counter() - start
    path = save_dataset(out, arrays, config)
    rate = (n_train + n_test) / seconds
    console.print(f"wrote {path}: {n_train} train + {n_test} test images, {rate:,.0f} images/s")


PresetOption = Annotated[
    str, typer.Option(metavar="paper|fast|smoke", help="Settings: paper, fast or smoke.")
]
DeviceOption = Annotated[
    str,
    typer.Option(metavar="auto|cpu|cuda", help="Where to train: auto (CUDA when there is one)."),
]


@vae_app.command("train")
def vae_train(
    out: Annotated[
        Path, typer.Option(help="Run folder (resumed if it holds an unfinished run).")
    ] = Path("runs/vae"),
    preset: PresetOption = "fast",
    epochs: Annotated[int | None, typer.Option(help="Override the preset's epochs.")] = None,
    seed: Annotated[
        int | None, typer.Option(help="Override the seed of weights and noise.")
    ] = None,
    dataset: Annotated[
        Path | None, typer.Option(help="Train on a file from `imagine dataset` instead.")
    ] = None,
    env: Annotated[
        str | None,
        typer.Option(
            metavar="ENV_ID",
            help="Train on another image environment's frames (a random policy's), resized "
            "to 64 x 64 RGB.",
        ),
    ] = None,
    wrapper: WrapperOption = None,
    device: DeviceOption = "auto",
    set_: VisionSetOption = None,
) -> None:
    """Train V on synthesized images, a dataset file or an env's frames; then its classifier.

    Per-epoch losses go to OUT/metrics.csv and OUT/tensorboard; run again to resume. The latent
    classifier (GesturePuzzle's macrostates) is fitted for GesturePuzzle's images only."""
    from imagine.config import parse_assignments, vision_preset
    from imagine.models.vision_training import resolve_device, resume_point, train_vae, with_dataset

    overrides = parse_assignments(set_ or [])
    overrides |= {k: v for k, v in {"epochs": epochs, "seed": seed}.items() if v is not None}
    if env is not None:
        overrides |= {"env": env, "env_wrappers": list(wrapper or [])}
    config = vision_preset(preset, **overrides)
    if dataset is not None:
        config = with_dataset(config, dataset)
    resolve_device(device)  # errors before any progress bar is drawn
    resume_point(out, config)
    start = time.perf_counter()
    columns = (TextColumn("training V"), BarColumn(), MofNCompleteColumn())
    with Progress(
        *columns, TextColumn("{task.fields[loss]}"), TimeRemainingColumn(), console=console
    ) as bar:
        task_id = bar.add_task("epochs", total=config.epochs, loss="")

        def on_epoch(epoch: int, row: dict[str, float]) -> None:
            loss = f"test rec {row['test/reconstruction']:.1f} kl {row['test/kl']:.2f}"
            bar.update(task_id, completed=epoch, loss=loss)

        train_vae(config, out, on_epoch=on_epoch, device=device)
    console.print(
        f"V trained in {out} ({time.perf_counter() - start:.0f} s); next: imagine vae report {out}",
        soft_wrap=True,
    )


@vae_app.command("report")
def vae_report(
    run: Annotated[Path, typer.Argument(help="A V run folder.")],
    agent: Annotated[
        Path | None, typer.Option(help="An agent run trained with this V: add M's accuracy.")
    ] = None,
) -> None:
    """Print V's quality numbers; write reconstructions.png and traversals.png into RUN.

    The numbers: test reconstruction loss and KL per image, each latent dimension's KL and
    whether it has collapsed, how far apart the macrostates lie against the spread of one
    macrostate's images, the MLP and linear probes' accuracy on fresh images, how often a draw
    of a perfect M (diagonal Gaussians fitted to each macrostate's latents) is read back right,
    and (--agent) the accuracy of an agent's M in this V's latent space."""
    from rich.table import Table

    from imagine.envs.gesture_puzzle.vision_report import report_run
    from imagine.models.vision_training import load_vae

    gesture_puzzle_only(load_vae(run)[1].env or ENV_ID, "imagine vae report")
    report, epoch = report_run(run)
    table = Table(title=f"V after {epoch} epochs ({run})")
    table.add_column("measure")
    table.add_column("value", justify="right")
    table.add_row(
        "test reconstruction (BCE per image)", f"{report['test_reconstruction_per_image']:.1f}"
    )
    table.add_row("test KL per image (nats)", f"{report['test_kl_per_image']:.2f}")
    kl = " ".join(f"{x:.2f}" for x in report["kl_per_dimension"])
    table.add_row("KL per dimension (nats)", kl)
    table.add_row("posterior sigma per dimension",
                  " ".join(f"{x:.2f}" for x in report["sigma_per_dimension"]))  # fmt: skip
    collapsed = report["collapsed_dimensions"]
    table.add_row(
        "active dimensions (collapsed)",
        f"{report['active_dimensions']} ({', '.join(map(str, collapsed)) or 'none'})",
    )
    for name in ("between", "within"):
        spread = " ".join(f"{x:.2f}" for x in report[f"{name}_std_per_dimension"])
        table.add_row(f"spread of mu {name} macrostates per dimension", spread)
    table.add_row(
        "nearest macrostate mean (min / median) vs an image from its own",
        f"{report['nearest_macrostate_distance_min']:.2f} / "
        f"{report['nearest_macrostate_distance_median']:.2f} vs "
        f"{report['within_macrostate_distance']:.2f} (ratio {report['separation_ratio']:.2f})",
    )
    for probe in ("classifier", "linear_probe"):
        for name, value in report[f"{probe}_accuracy"].items():
            label = "MLP probe" if probe == "classifier" else "linear probe"
            table.add_row(f"{label} accuracy: {name}", f"{100 * value:.2f}%")
    for name, value in report["diagonal_draw_accuracy"].items():
        if name.startswith("scale_"):  # fitted to each macrostate's cloud of V's means
            label = f"right draws, 1 diagonal comp., x {name.removeprefix('scale_')}"
        else:
            label = f"right draws, {name.removeprefix('components_')} diagonal comps."
        table.add_row(label, f"{100 * value:.1f}%")
    if agent is not None:
        from imagine.envs.gesture_puzzle.vision_report import agent_model_accuracy

        for name, value in agent_model_accuracy(run, agent).items():
            table.add_row(f"M accuracy ({agent}): {name}", f"{100 * value:.1f}%")
    Console().print(table)
    console.print(
        f"wrote {run / 'reconstructions.png'}, {run / 'traversals.png'}, {run / 'report.json'}"
    )


class MethodName(StrEnum):
    baseline = "baseline"
    augmented = "augmented"


def with_options(overrides: dict[str, Any], given: dict[str, tuple[str, Any]]) -> dict[str, Any]:
    """``overrides`` (from --config and --set) with the fields that options gave (``given``:
    field -> (option, value or None when not given)); a field given both ways must agree."""
    merged = dict(overrides)
    for key, (option, value) in given.items():
        if value is None:
            continue
        if key in merged and merged[key] != value:
            raise ImagineError(
                f"{key} is given twice, differently: {option} {value} and {key}={merged[key]!r} "
                "(--set or --config)"
            )
        merged[key] = value
    return merged


def gesture_puzzle_only(env: str, what: str) -> None:
    """A one-line error for GesturePuzzle's extras asked of another environment's run."""
    if env != ENV_ID:
        raise ImagineError(f"{what} is GesturePuzzle's (its rules and states); this run is {env}")


RECENT = 20
"""The training bar's return and success: the mean of each agent's last RECENT episodes."""


def recent_outcome(recent: list[deque]) -> str:
    """The mean return (and success, where the environment reports it) of the episodes in
    ``recent`` (per agent, (return, success) pairs), as the training bar shows it."""
    pairs = [pair for episodes in recent for pair in episodes]
    returns = [r for r, _ in pairs if r is not None]
    if not returns:
        return ""
    text = f"return {sum(returns) / len(returns):.2f}"
    successes = [s for _, s in pairs if s is not None]
    if successes:
        text += f", success {100 * sum(successes) / len(successes):.0f}%"
    return text + f" (last {max(len(episodes) for episodes in recent)} episodes)"


def saved_counts(folder: Path) -> tuple[int, int]:
    """(episodes, real time steps) of the run checkpointed in ``folder``; (0, 0) if none (or
    if it holds another thing, such as a saved agent, which training refers to)."""
    from imagine.checkpoint import read_json
    from imagine.learning.agent_checkpoint import FORMAT

    if not (folder / "agent.json").is_file():
        return 0, 0
    meta = read_json(folder / "agent.json", "agent checkpoint metadata")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        return 0, 0
    return int(meta.get("episode", 0)), int(meta.get("t", 0))


@app.command("train")
def train_agent(
    out: Annotated[
        Path, typer.Argument(help="Run folder (resumed if it holds an unfinished run).")
    ],
    task: Annotated[TaskName | None, typer.Option(help="The task (default: original).")] = None,
    method: Annotated[
        MethodName | None, typer.Option(help="Algorithm 1 with or without M (default: augmented).")
    ] = None,
    episodes: Annotated[int | None, typer.Option(help="Training episodes.")] = None,
    steps: Annotated[
        int | None,
        typer.Option(help="A budget of real time steps (alone: no episode budget)."),
    ] = None,
    env: Annotated[
        str | None,
        typer.Option(
            metavar="ENV_ID",
            help="Any registered Gymnasium environment with Discrete actions, as "
            "gymnasium.make takes it (module:Id included; default: GesturePuzzle).",
        ),
    ] = None,
    wrapper: WrapperOption = None,
    seed: Annotated[int | None, typer.Option(help="Seed of everything random (default 0).")] = None,
    seeds: Annotated[
        str | None,
        typer.Option(
            metavar="SEEDS",
            help="Seeds trained together as one population, e.g. 0,1,2 or 0-4, each into "
            "OUT/seed-N (each with exactly its numbers alone).",
        ),
    ] = None,
    preset: PresetOption = "fast",
    vae: Annotated[Path | None, typer.Option(help="V run folder (imagine vae train).")] = None,
    oracle: Annotated[
        bool | None,
        typer.Option("--oracle/--no-oracle", help="Feed C and M the true macrostate's embedding."),
    ] = None,
    init_from: Annotated[
        Path | None,
        typer.Option(
            help="A trained run (or folder of seed-N runs) whose M's MDN starts this "
            "agent's: the dynamics transfer, r, d and C start fresh."
        ),
    ] = None,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
    device: DeviceOption = "auto",
    config_file: Annotated[
        Path | None,
        typer.Option("--config", help="YAML mapping of agent config fields over the preset."),
    ] = None,
    set_: SetOption = None,
) -> None:
    """Train one agent with Algorithm 1 (paper section V-B), or several in lockstep.

    Writes its config, metrics (CSV and TensorBoard) and checkpoints into OUT; run it again to
    resume. A field set both by an option and by --set or --config must agree. With --env, the
    encoder follows the observations: vectors as they are, Discrete as one-hot."""
    import dataclasses

    from imagine.config import (
        agent_preset,
        check_imagines,
        load_yaml,
        parse_assignments,
        parse_seeds,
    )
    from imagine.devices import resolve_device
    from imagine.errors import NumericalError
    from imagine.learning.agent import (
        UNBOUNDED_EPISODES,
        check_folder,
        make_encoder,
        with_encoder_of_env,
    )
    from imagine.learning.training import train_population

    overrides: dict = load_yaml(config_file) if config_file is not None else {}
    overrides |= parse_assignments(set_ or [])
    given = {
        "task": ("--task", None if task is None else task.value),
        "method": ("--method", None if method is None else method.value),
        "seed": ("--seed", seed),
        "episodes": ("--episodes", episodes),
        "steps": ("--steps", steps),
        "env": ("--env", env),
        "wrappers": ("--wrapper", wrapper or None),
        "encoder": ("--oracle", None if oracle is None else "oracle" if oracle else "vae"),
        "vae_run": ("--vae", None if vae is None else str(vae)),
        "init_from": ("--init-from", None if init_from is None else str(init_from)),
    }
    values = with_options(overrides, given)
    if values.get("env", ENV_ID) != ENV_ID and "steps" not in values and "episodes" not in values:
        raise ImagineError(
            f"--env {values['env']} needs a budget: give --steps N, real time steps "
            "(e.g. --steps 20000), or --episodes N"
        )
    if "steps" in values and "episodes" not in values:
        values["episodes"] = UNBOUNDED_EPISODES
    values = with_encoder_of_env(values)
    config = check_imagines(agent_preset(preset, **values))
    if seeds is None:
        configs, folders = [config], [out]
    else:
        chosen = parse_seeds(seeds)
        configs = [dataclasses.replace(config, seed=s) for s in chosen]
        folders = [out / f"seed-{s}" for s in chosen]
    for c, folder in zip(configs, folders, strict=True):
        check_folder(c, folder)  # errors before any progress bar is drawn
    counts = [saved_counts(folder) for folder in folders]
    finished = [e >= c.episodes or 0 < c.steps <= t
                for c, (e, t) in zip(configs, counts, strict=True)]  # fmt: skip
    for folder, (e, t), done_already in zip(folders, counts, finished, strict=True):
        if done_already:
            message = (f"{folder} is finished ({e} episodes, {t} time steps); nothing to train "
                       "(a larger --episodes or --steps trains on)")  # fmt: skip
            console.print(message, soft_wrap=True)
    if all(finished):
        return
    torch_device = resolve_device(device)
    encoder = make_encoder(config, torch_device)
    start = time.perf_counter()
    label = f"seed {config.seed}" if seeds is None else f"seeds {seeds}"
    what = config.task if config.env == ENV_ID else config.env
    by_steps = config.steps > 0 and config.episodes == UNBOUNDED_EPISODES
    budget = config.steps if by_steps else config.episodes
    done = [min(t, budget) if by_steps else e for e, t in counts]
    recent: list[deque] = [deque(maxlen=RECENT) for _ in configs]  # (return, success)
    with Bar(f"{config.method} {what} {label}", budget * len(configs),
             "steps" if by_steps else "episodes", sum(done)) as bar:  # fmt: skip

        def on_episode(i: int, episode: int, t: int, stats: dict[str, float]) -> None:
            done[i] = min(t, budget) if by_steps else episode
            recent[i].append((stats.get("charts/return"), stats.get("charts/success")))
            bar.update(sum(done), recent_outcome(recent))

        result = train_population(configs, folders, on_episode, threads=threads,
                                  encoder=encoder, device=str(torch_device))  # fmt: skip
    seconds = time.perf_counter() - start
    for i, agent in enumerate(result.agents):
        if agent is not None and not finished[i]:
            steps = f"{agent.episode} episodes, {agent.t} time steps"
            console.print(f"trained {folders[i]}: {steps}; next: imagine evaluate {folders[i]}",
                          soft_wrap=True)  # fmt: skip
    console.print(f"trained in {seconds:.0f} s", soft_wrap=True)
    if result.failures:
        raise NumericalError("; ".join(result.failures.values()))


@app.command("evaluate")
def evaluate_agent(
    run: Annotated[Path, typer.Argument(help="An agent run folder.")],
    episodes: Annotated[
        int | None,
        typer.Option(
            help="Greedy test episodes (default: the run's eval_episodes, 1000; 200 with the "
            "smoke preset)."
        ),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the test episodes.")] = 1_000_000,
) -> None:
    """Test an agent: greedy success, M's accuracy, the imagined transitions' quality.

    Runs greedy test episodes (batched) and prints the success rate with its 95% interval, M's
    accuracy over all 192 x 6 true transitions, and how right the transitions are that M
    imagines for C (judged by V's latent classifier); how well the members' disagreement (an
    ensemble M) and the support distance detect the wrong ones (AUROC), and how right the
    transitions its gate accepts and rejects are."""
    from imagine.checkpoint import write_json
    from imagine.envs.gesture_puzzle.evaluation import (
        agent_success,
        hand_calibration,
        imagined_accuracy,
        model_accuracy,
    )
    from imagine.learning.agent import load_agent
    from imagine.learning.imagination import actions_at

    agent = load_agent(run)
    n = episodes or agent.config.eval_episodes
    if agent.config.env != ENV_ID:
        evaluate_any(run, agent, n, seed)
        return
    p = agent.config.hand_switch_prob
    result = agent_success(agent, n, seed)
    accuracy = imagined = imagined_other = calibration = calibration_all = None
    other = "mode" if agent.config.imagination_draw == "sample" else "sample"
    if agent.config.trains_model:
        accuracy = model_accuracy(agent.model, agent.encoder, agent.config.task, p)
        calibration = hand_calibration(agent.model, agent.encoder, agent.config.task, p)
        calibration_all = hand_calibration(agent.model, agent.encoder, agent.config.task, p,
                                           include_terminal=True)  # fmt: skip
        imagined = imagined_accuracy(agent)
        imagined_other = imagined_accuracy(agent, draw=other)
    detection = None if imagined is None else imagined.get("disagreement_auroc")
    support = None if imagined is None else imagined.get("support_auroc")
    write_json(run / "evaluation.json", {
        "after_episodes": agent.episode, **result, "model_accuracy": accuracy,
        "imagined_accuracy": imagined, f"imagined_accuracy_{other}": imagined_other,
        "imagined_disagreement_auroc": detection, "hand_calibration": calibration,
        "hand_calibration_all": calibration_all, "imagined_support_auroc": support})  # fmt: skip
    print(f"{run}: {agent.config.method}, task {agent.config.task}, after {agent.episode} episodes")
    low, high = 100 * result["ci_low"], 100 * result["ci_high"]
    print(f"success {100 * result['success']:.1f}% (95% CI [{low:.1f}, {high:.1f}]%), {n} "
          "episodes; mean return {mean_return:.2f} (95% CI [{return_ci_low:.2f}, "
          "{return_ci_high:.2f}])".format(**result))  # fmt: skip
    if "success_observation" in result:
        print(f"C acts on a filtered belief (w = {agent.config.filter_weight}); on V's means "
              f"alone it succeeds {100 * result['success_observation']:.1f}%")  # fmt: skip
    if accuracy is None:
        print("M accuracy: not measured (a baseline run does not train M)")
        return
    print("M accuracy: transition {transition:.1%} (non-terminal {transition_nonterminal:.1%}, "
          "sampled {transition_sampled:.1%}), reward {reward:.1%}, terminal {terminal:.1%}"
          .format(**accuracy))  # fmt: skip
    if "hand_kept_sampled" in accuracy:
        print(f"stochastic human: M's draws keep the hand {accuracy['hand_kept_sampled']:.1%} "
              f"of the time (truth {1 - p:.1%}); its mixture's weight: hand kept "
              "{kept:.1%}, moved {moved_next:.1%} / {moved_previous:.1%} (truth {half:.1%} "
              "each), wrong state {wrong:.1%}, total variation {total_variation:.3f} "
              "(from non-terminal states; {all:.3f} over all 192 x 6 transitions)"
              .format(half=p / 2, all=calibration_all["total_variation"],
                      **calibration))  # fmt: skip
    from_memory = agent.config.imagination_from == "memory" and agent.memory_starts is not None
    where = "M_R" if from_memory else "new episodes"
    every = actions_at(agent.config, agent.episode) == "all"
    shape = "I_B x A, one step" if every else "I_B x I_D"
    print(f"imagined transitions ({agent.config.imagination_draw}, as in training; 100 start "
          f"states from {where}, {shape}) right: "
          "state {state:.1%} (first step {first_step:.1%}), reward "
          "{reward:.1%} (mean error of r {reward_error:.2f}), terminal {terminal:.1%}"
          .format(**imagined))  # fmt: skip
    print(f"the same M with imagination_draw={other}: state {{state:.1%}}, reward "
          "{reward:.1%}, terminal {terminal:.1%}".format(**imagined_other))  # fmt: skip
    if detection is not None:
        print(f"disagreement of M's {agent.config.model_ensemble} members as a detector of wrong "
              f"imagined states: {auroc_text(detection, imagined['state'])}; state right in "
              "the most-agreed half {state_agreed_half:.1%}, in the rest "
              "{state_disagreed_half:.1%}".format(**imagined))  # fmt: skip
    if support is not None:
        print(
            f"support (distance to M_R's nearest start with the same action) as a detector of "
            f"wrong imagined states: {auroc_text(support, imagined['state'])}"
        )
    if "accepted" in imagined:
        gate = agent.config.imagination_gate
        rule = f"gate {gate}" if gate != "none" else "gate mask (the agent has none)"
        rule += f" on {agent.config.imagination_uncertainty}"
        print(f"{rule} at q {agent.config.imagination_gate_quantile}, scale "
              f"{agent.config.imagination_gate_scale}: threshold {{gate_threshold:.3f}}, accepts "
              "{accepted:.1%}; state right in the accepted {state_accepted:.1%}, in the rejected "
              "{state_rejected:.1%}".format(**imagined))  # fmt: skip


def auroc_text(value: float, state_right: float) -> str:
    """``AUROC 0.812``, or ``AUROC n/a`` with the reason where there is none: a detector of
    wrong imagined states needs both wrong and right ones (``state_right``: their share)."""
    if not math.isnan(value):
        return f"AUROC {value:.3f}"
    if state_right >= 1:
        why = "every imagined state was right, none wrong to detect"
    elif state_right <= 0:
        why = "every imagined state was wrong, none right to tell them from"
    else:
        why = "undefined on these transitions"
    return f"AUROC n/a ({why})"


def evaluate_any(run: Path, agent, episodes: int, seed: int) -> None:
    """``imagine evaluate`` for an environment other than GesturePuzzle: greedy test episodes'
    mean return (and success where the environment reports it) into RUN/evaluation.json."""
    from imagine.checkpoint import write_json
    from imagine.envs.spec import make_spec
    from imagine.learning.test_episodes import agent_policy, circling, run_episodes

    spec = make_spec(agent.config)
    result = run_episodes(spec, agent_policy(agent, episodes), episodes, seed)
    write_json(run / "evaluation.json", {"after_episodes": agent.episode, "after_steps": agent.t,
                                         **result})  # fmt: skip
    print(f"{run}: {agent.config.method}, {agent.config.env}, after {agent.t} time steps "
          f"({agent.episode} episodes)")  # fmt: skip
    print(
        "mean return {mean_return:.2f} (95% CI [{return_ci_low:.2f}, {return_ci_high:.2f}]), "
        "mean length {mean_length:.1f}, {episodes} greedy episodes".format(**result)
    )
    if "success" in result:
        print(f"success {100 * result['success']:.1f}% (95% CI [{100 * result['ci_low']:.1f}, "
              f"{100 * result['ci_high']:.1f}]%)")  # fmt: skip
    if result["truncated"] > 0 and spec.kind == "vector":
        loops = circling(spec, agent_policy(agent, 1, copies=1), min(episodes, 100), seed)
        write_json(run / "evaluation.json", {"after_episodes": agent.episode,
                                             "after_steps": agent.t, **result,
                                             "circling": loops})  # fmt: skip
        print(f"{100 * result['truncated']:.0f}% of the greedy episodes ran to the time limit; "
              f"of those, {100 * loops['circling']:.0f}% circle (their last state comes back, "
              f"median period {loops['median_period']:g} steps), and an episode's most "
              f"frequent action is {100 * loops['one_action']:.0f}% of its actions "
              f"({loops['episodes']} episodes)")  # fmt: skip


@app.command("compare")
def compare_command(
    env: Annotated[
        str,
        typer.Option(metavar="ENV_ID", help="A registered Gymnasium env with Discrete actions."),
    ],
    out: Annotated[Path, typer.Option(help="Folder of the runs, table and figure (resumed).")],
    steps: Annotated[
        str, typer.Option(metavar="N,N,...", help="Environment-step budgets, e.g. 10000,20000.")
    ] = "10000,20000",
    seeds: Annotated[str, typer.Option(metavar="SEEDS", help="Seeds, e.g. 0-4.")] = "0-4",
    wrapper: WrapperOption = None,
    vae: Annotated[Path | None, typer.Option(help="V run for image observations.")] = None,
    episodes: Annotated[int, typer.Option(min=1, help="Greedy test episodes per agent.")] = 100,
    methods: Annotated[
        str,
        typer.Option(
            metavar="M,M,...",
            help="Which to train now (the table shows all under OUT): baseline, control (the "
            "baseline with the augmented agent's C updates per step), augmented, sb3-dqn.",
        ),
    ] = "baseline,augmented,sb3-dqn",
    preset: PresetOption = "fast",
    set_: SetOption = None,
) -> None:
    """Our baseline and augmented agents beside Stable-Baselines3's DQN at equal env steps.

    Each method, each seed, each budget: the mean return of the same greedy test episodes.
    Writes OUT/comparison.md (mean, std, IQM with 95% bootstrap CI), OUT/comparison.json and
    OUT/comparison.png (IQM against steps). SB3 (RL Zoo settings where tuned) needs the
    optional extra: pip install 'imagine[sb3]'; without it its row is skipped."""
    from imagine.config import agent_preset, parse_assignments, parse_seeds
    from imagine.learning.agent import UNBOUNDED_EPISODES, with_encoder_of_env
    from imagine.study.compare import (
        METHODS,
        arm_settings,
        report,
        sb3_available,
        train_ours,
        train_sb3,
    )

    try:
        budgets = sorted({int(x) for x in steps.split(",")})
    except ValueError:
        raise ImagineError(f"--steps expects comma-separated integers, got {steps!r}") from None
    if not budgets or budgets[0] < 1:
        raise ImagineError(f"--steps budgets must be positive, got {steps!r}")
    chosen = parse_seeds(seeds)
    wanted = [m.strip() for m in methods.split(",") if m.strip()]
    if not wanted or set(wanted) - set(METHODS):
        raise ImagineError(f"--methods takes {', '.join(METHODS)}; got {methods!r}")
    values = parse_assignments(set_ or []) | {"env": env, "wrappers": list(wrapper or []),
                                              "episodes": UNBOUNDED_EPISODES}  # fmt: skip
    if vae is not None:
        values["vae_run"] = str(vae)
    values = with_encoder_of_env(values)
    out.mkdir(parents=True, exist_ok=True)
    for arm in [m for m in ("baseline", "control", "augmented") if m in wanted]:
        config = agent_preset(preset, **arm_settings(values, arm), steps=budgets[0])
        train_ours(config, out, chosen, budgets, episodes, log=console.print, arm=arm)
    if "sb3-dqn" in wanted and sb3_available():
        train_sb3(env, list(wrapper or []), out, chosen, budgets, episodes, log=console.print)
    elif "sb3-dqn" in wanted:
        console.print("sb3-dqn skipped: stable-baselines3 is not installed "
                      "(pip install 'imagine[sb3]')")  # fmt: skip
    table, png = report(env, out)
    console.print(table)
    console.print(f"wrote {out / 'comparison.md'} and {png}")


@app.command("bench")
def bench_command(
    suite: Annotated[Path, typer.Argument(metavar="SUITE", help="A suite file (suites/*.yaml).")],
    out: Annotated[Path, typer.Argument(metavar="OUT", help="Folder of the runs (resumed).")],
    envs: Annotated[
        str | None,
        typer.Option(metavar="ID,ID,...", help="Only these of the suite's environments."),
    ] = None,
    arms: Annotated[
        str | None,
        typer.Option(
            metavar="A,A,...",
            help="Only these arms: baseline, control, augmented, sb3-dqn (the report shows "
            "all under OUT).",
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option(min=1, help="(environment, arm) cells at once, one thread each.")
    ] = 2,
    up_to: Annotated[
        int | None,
        typer.Option(
            metavar="STEPS",
            min=1,
            help="Only the budgets up to STEPS (a later run without it goes on).",
        ),
    ] = None,
) -> None:
    """The sample-efficiency suite: every arm on every environment, seed and budget.

    Arms: the paper's baseline, the replay-ratio control (the baseline with as many C updates
    per real step as the augmented agent), the augmented agent and SB3's DQN, all judged by
    the same greedy test episodes. Writes OUT/SUITE.md (per environment mean, std and IQM
    with 95% bootstrap CI; scores normalised by a random policy and the suite's reference;
    where imagination hurts or pays) and each environment's table and figure; rerun to
    resume."""
    from imagine.study.suite import ARMS, check_suite, load_suite, run_suite

    if not suite.is_file():
        raise ImagineError(f"no suite file {suite}")
    loaded = load_suite(suite)
    names = [e.env for e in loaded.environments]
    chosen_envs = None if envs is None else [e.strip() for e in envs.split(",") if e.strip()]
    if chosen_envs is not None and (not chosen_envs or set(chosen_envs) - set(names)):
        raise ImagineError(f"--envs takes the suite's {', '.join(names)}; got {envs!r}")
    chosen_arms = None if arms is None else [a.strip() for a in arms.split(",") if a.strip()]
    if chosen_arms is not None and (not chosen_arms or set(chosen_arms) - set(ARMS)):
        raise ImagineError(f"--arms takes {', '.join(ARMS)}; got {arms!r}")
    check_suite(loaded)
    path = run_suite(loaded, out, chosen_envs, chosen_arms, workers, console.print, up_to)
    console.print(f"wrote {path}")


@app.command("plan")
def plan_command(
    run: Annotated[Path, typer.Argument(help="An agent run folder.")],
    trials: Annotated[int, typer.Option(min=1, help="Plans from random start states.")] = 20,
    seed: Annotated[int, typer.Option(help="Seed of the start states and images.")] = 0,
) -> None:
    """Plan with M and C from one observation (paper section V, Generating Plans).

    Generates plans, executes them open-loop and compares their length with the optimal;
    writes RUN/plans.json and RUN/plan_rollout.png (V's decoding of an imagined plan of
    length 5, paper Fig. 5)."""
    from imagine.checkpoint import write_json
    from imagine.learning.agent import load_agent
    from imagine.study.planning import plan_trials, rollout_png, summarize_plans

    agent = load_agent(run)
    gesture_puzzle_only(agent.config.env, "planning")
    summary = summarize_plans(plan_trials(agent, trials, seed))
    write_json(run / "plans.json", summary)
    png = rollout_png(agent, run / "plan_rollout.png", seed=seed)
    print(f"{run}: {summary['successes']} of {trials} plans succeeded, "
          f"{summary['optimal']} optimal (paper: 17 of 20, every success optimal)")  # fmt: skip
    print(f"wrote {run / 'plans.json'}" + (f" and {png}" if png else ""))


@app.command("generalize")
def generalize_command(
    run: Annotated[Path, typer.Argument(help="An agent run folder.")],
    trials: Annotated[
        int, typer.Option(min=1, help="Random (terminal state, action) trials.")
    ] = 20,
    seed: Annotated[int, typer.Option(help="Seed of the trials and images.")] = 0,
) -> None:
    """M's next state from terminal states it never trained on (paper Fig. 7).

    Paper section V, Model Generalization: the 20-trial test and all terminal states x
    actions; writes RUN/generalization.json and RUN/generalization.png (paper Fig. 7)."""
    from imagine.checkpoint import write_json
    from imagine.learning.agent import load_agent
    from imagine.study.generalization import generalization, generalization_png

    agent = load_agent(run)
    gesture_puzzle_only(agent.config.env, "the generalization test")
    result = generalization(agent, trials, seed)
    write_json(run / "generalization.json", result)
    png = generalization_png(agent, run / "generalization.png", seed)
    print(f"{run}: {result['trials_right']} of {trials} right "
          f"({100 * result['trial_accuracy']:.0f}%; paper 75%); over all "
          f"{result['all_terminal_transitions']} terminal transitions "
          f"{100 * result['all_terminal_accuracy']:.1f}%")  # fmt: skip
    print(f"wrote {run / 'generalization.json'}" + (f" and {png}" if png else ""))


@app.command("study")
def study_command(
    files: Annotated[
        list[Path], typer.Argument(metavar="FILE", help="Experiment files (experiments/*.yaml).")
    ],
    out: Annotated[Path, typer.Option(help="Study folder (resumed if it holds one).")] = Path(
        "runs/study"
    ),
    tasks: Annotated[str, typer.Option(metavar="TASKS", help="Comma-separated tasks.")] = "hard",
    seeds: Annotated[
        str, typer.Option(metavar="SEEDS", help="Seeds of every (file, task), e.g. 0-4.")
    ] = "0-4",
    budgets: Annotated[
        str, typer.Option(metavar="BUDGETS", help="Comma-separated training-episode budgets.")
    ] = "1000,2000",
    vae: Annotated[Path | None, typer.Option(help="V run folder (imagine vae train).")] = None,
    oracle: Annotated[bool, typer.Option(help="Feed C and M the true macrostate.")] = False,
    workers: Annotated[int, typer.Option(help="Runs at once (one torch thread each).")] = 2,
) -> None:
    """Run experiment files (experiments/*.yaml) on tasks, seeds and budgets; rerun to resume.

    Each file's agents train on every task and seed, evaluated at every budget (the file's
    eval_episodes greedy test episodes). Prints and writes OUT/STUDY.md: success as mean (std)
    and IQM [95% CI] per task and budget. Every evaluation records its resolved config, the
    commit and V's hash."""
    from imagine.config import parse_seeds
    from imagine.study.experiment_file import experiment_jobs, load_experiment, study_table
    from imagine.study.experiments import LocalRunner, folder_lock

    if (vae is None) == (not oracle):
        raise ImagineError("imagine study needs --vae RUN or --oracle (one of them)")
    if vae is not None and not (vae / "vae.safetensors").is_file():
        raise ImagineError(f"--vae {vae}: not a V run folder (no vae.safetensors)")
    try:
        budget_list = tuple(sorted({int(x) for x in budgets.split(",")}))
    except ValueError:
        raise ImagineError(f"--budgets expects comma-separated integers, got {budgets!r}") from None
    task_list = tuple(t.strip() for t in tasks.split(",") if t.strip())
    experiments = [load_experiment(f) for f in files]
    names = [e.name for e in experiments]
    if len(set(names)) < len(names):
        raise ImagineError(f"two experiment files share a name: {', '.join(names)}")
    vae_run = None if vae is None else str(vae.resolve())
    jobs = {e.name: experiment_jobs(e, out, task_list, parse_seeds(seeds), budget_list, vae_run)
            for e in experiments}  # fmt: skip
    todo = [j for e in experiments for j in jobs[e.name] if not j.finished()]
    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with folder_lock(out, notice=console.print):
            LocalRunner(workers).run(
                todo, on_start=lambda job: None,
                on_done=lambda job, error: console.print(f"{job.folder}: {error or 'done'}"),
            )  # fmt: skip
    finally:  # stopped or not, the table of what has finished
        table = study_table(experiments, jobs, task_list, budget_list)
        (out / "STUDY.md").write_text(table + "\n")
        console.print(table, soft_wrap=True)
    console.print(f"studied in {time.perf_counter() - start:.0f} s; table: {out / 'STUDY.md'}")


class StudyProgress:
    """While a study runs, its bar every ``period`` seconds: the episodes its runs have
    trained (their metrics.csv files, which the worker processes write), with the recent
    success of the running ones (their last metrics row each) and their names."""

    def __init__(self, jobs, running: list[str], period: float = 5.0) -> None:
        import threading

        self.jobs, self.running, self.period = jobs, running, period
        self.total = sum(max(job.budgets) for job in jobs)
        self.stopped = threading.Event()

    @contextmanager
    def showing(self, bar: Bar) -> Iterator[None]:
        """Update ``bar`` from a thread while the block runs, and once at its end."""
        import threading

        def poll() -> None:
            while not self.stopped.wait(self.period):
                bar.update(*self.count())

        thread = threading.Thread(target=poll, daemon=True)
        thread.start()
        try:
            yield
        finally:
            self.stopped.set()
            thread.join()
            bar.update(*self.count())

    def count(self) -> tuple[int, str]:
        """The episodes trained so far, and what the bar says beside them."""
        from imagine.metrics import read_metrics

        done, successes = 0, []
        for job in self.jobs:
            budget = max(job.budgets)
            metrics = Path(job.folder) / "metrics.csv"
            if job.finished():
                done += budget
            elif metrics.is_file():
                rows = read_metrics(metrics)
                done += min(int(rows[-1]["step"]), budget) if rows else 0
                if rows and job.name in self.running and "charts/success" in rows[-1]:
                    successes.append(rows[-1]["charts/success"])
        running = list(self.running)
        info = ""
        if successes:
            info = f"success {100 * sum(successes) / len(successes):.0f}% (running runs' last rows)"
        if running:
            info += ("; " if info else "") + "running: " + ", ".join(running)
        return done, info


@app.command("reproduce")
def reproduce_study(
    out: Annotated[Path, typer.Argument(help="Study folder (resumed if it holds one).")],
    preset: PresetOption = "fast",
    tasks: Annotated[
        str, typer.Option(metavar="TASKS", help="Comma-separated tasks.")
    ] = "original,hard",
    seeds: Annotated[
        str,
        typer.Option(metavar="SEEDS", help="The seeds of every (task, method), e.g. 0,1,2 or 0-4."),
    ] = "0-4",
    budgets: Annotated[
        str, typer.Option(metavar="BUDGETS", help="Comma-separated training-episode budgets.")
    ] = "250,500,1000,1500,2000,3000,4000,5000,6000",
    backend: Annotated[
        str, typer.Option(metavar="local|ray", help="Processes on this machine, or Ray.")
    ] = "local",
    workers: Annotated[int, typer.Option(help="Runs at once (one torch thread each).")] = 2,
    address: Annotated[
        str | None,
        typer.Option(metavar="HOST:PORT", help="Address of an existing Ray cluster (ray backend)."),
    ] = None,
    vae: Annotated[
        Path | None, typer.Option(help="Reuse this V run instead of training V into OUT/vae.")
    ] = None,
    oracle: Annotated[bool, typer.Option(help="Feed C and M the true macrostate.")] = False,
    separate_runs: Annotated[
        bool, typer.Option(help="One run per budget from scratch (default: one run per seed).")
    ] = False,
    device: DeviceOption = "auto",
    set_: SetOption = None,
    baselines: Annotated[
        str,
        typer.Option(
            metavar="BASELINES",
            help="Peer baselines beside ours: sb3 (Stable-Baselines3's DQN, pip install "
            "'imagine[sb3]'; skipped in one line without it).",
        ),
    ] = "",
) -> None:
    """The paper's section V in one command; run it again to resume.

    V, every (task, method, seed) agent evaluated at every budget, Tables I and II, figures and
    REPORT.md, all in OUT."""
    from imagine.config import parse_assignments, parse_seeds
    from imagine.study.experiments import folder_lock, study_jobs
    from imagine.study.reproduce import StudyConfig, reproduce

    def numbers(text: str, name: str) -> tuple[int, ...]:
        try:
            return tuple(int(x) for x in text.split(","))
        except ValueError:
            raise ImagineError(f"--{name} expects comma-separated integers, got {text!r}") from None

    config = StudyConfig(
        preset=preset, tasks=tuple(t.strip() for t in tasks.split(",")),
        seeds=parse_seeds(seeds),
        budgets=numbers(budgets, "budgets"), backend=backend, workers=workers, address=address,
        vae_run=None if vae is None else str(vae), oracle=oracle, separate_runs=separate_runs,
        overrides=parse_assignments(set_ or []), device=device,
        baselines=tuple(b.strip() for b in baselines.split(",") if b.strip()),
    )  # fmt: skip
    if len(config.seeds) == 1 and config.seeds[0] > 1:  # `--seeds 5` once meant five seeds
        console.print(f"note: --seeds {seeds} is seed {config.seeds[0]} alone; five seeds are "
                      "--seeds 0-4")  # fmt: skip
    start = time.perf_counter()
    jobs = study_jobs(out, config.tasks, config.seeds, config.budgets,
                      separate_runs=separate_runs)  # fmt: skip
    running: list[str] = []
    progress = StudyProgress(jobs, running)
    with (
        folder_lock(out, notice=console.print),  # refused before any bar shows
        Bar("study", progress.total, "episodes", progress.count()[0]) as bar,
        progress.showing(bar),
    ):

        def on_start(job) -> None:
            running.append(job.name)

        def on_done(job, error) -> None:
            running.remove(job.name)
            if error is not None and "Interrupted" not in error:
                console.print(f"[red]failed[/red] {escape(error)}")

        def log(message: str) -> None:
            console.print(message)

        report, failures = reproduce(config, out, log, on_start, on_done)
    console.print(f"study done in {time.perf_counter() - start:.0f} s; report: {report}",
                  soft_wrap=True)  # fmt: skip
    if failures:
        console.print(f"{len(failures)} run(s) failed; see {report}")
        raise typer.Exit(1)


def main() -> None:
    """Entry point of the `imagine` command."""
    from imagine.errors import Interrupted

    try:
        app()
    except Interrupted as exc:
        console.print(f"stopped: {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(128 + exc.signal_number)
    except (ImagineError, OSError) as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(2)
