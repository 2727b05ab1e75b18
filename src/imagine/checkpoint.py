"""Checkpoints and result files: safetensors plus a JSON document, written atomically.

Nothing here unpickles: tensors go through safetensors, everything else (configs, counters,
random generator states as integer lists) through JSON. Every write goes to a temporary file in
the same folder and is then renamed over the target, so a reader never sees half a file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from imagine.errors import CheckpointError


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def fsync_file(path: str | Path) -> None:
    """Flush a written file to disk, so the rename that follows never exposes an empty file
    after a power cut."""
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def save_figure(fig: Any, out: str | Path, dpi: int = 90) -> Path:
    """A matplotlib figure as PNG, atomically: a temporary file, then a rename."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    fig.savefig(tmp, dpi=dpi, format="png")
    os.replace(tmp, out)
    return out


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def write_json(path: str | Path, document: Any) -> Path:
    return atomic_write_text(path, json.dumps(document, indent=2, sort_keys=True) + "\n")


def with_defaults(cls: type, saved: Mapping[str, Any]) -> dict[str, Any]:
    """A recorded config of dataclass ``cls`` with the fields added since it was written at
    their defaults, as JSON values: a new field's default is the behaviour of the code before
    it (the project's rule for new fields), so a record that lacks it measured that default."""
    defaults = {f.name: f.default if f.default_factory is dataclasses.MISSING
                else f.default_factory() for f in dataclasses.fields(cls)}  # fmt: skip
    return {**json.loads(json.dumps(defaults)), **saved}


def changed_fields(saved: Mapping[str, Any], asked: Mapping[str, Any], skip=()) -> str:
    """The fields whose value differs between a saved config and the one asked for, as
    ``name old -> new`` joined by commas (``skip``: fields allowed to differ), in the
    order of ``asked``."""
    names = [*asked, *(k for k in saved if k not in asked)]
    return ", ".join(
        f"{name} {saved.get(name)!r} -> {asked.get(name)!r}"
        for name in names
        if name not in skip and saved.get(name) != asked.get(name)
    )


def read_json(path: str | Path, what: str = "file") -> Any:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{what} {path} does not exist")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{what} {path} is not valid JSON ({exc})") from None


def save_tensors(path: str | Path, tensors: Mapping[str, torch.Tensor]) -> Path:
    """Save tensors as safetensors, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    save_file({k: v.detach().contiguous().cpu() for k, v in tensors.items()}, str(tmp))
    fsync_file(tmp)
    os.replace(tmp, path)
    return path


def load_tensors(path: str | Path, what: str = "checkpoint") -> dict[str, torch.Tensor]:
    """Load a safetensors file; a one-line :class:`CheckpointError` for a missing, truncated or
    foreign file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{what} {path} does not exist")
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{what} {path} is corrupt or not safetensors ({exc})") from None


def load_state_dict_strict(
    module: torch.nn.Module, tensors: Mapping[str, torch.Tensor], what: str
) -> None:
    """Load ``tensors`` into ``module``, naming the first mismatch in one line."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        detail = f"missing {missing[:3]}" if missing else f"unexpected {unexpected[:3]}"
        raise CheckpointError(f"{what} does not fit this architecture: {detail}")
    for key, value in expected.items():
        if tensors[key].shape != value.shape:
            raise CheckpointError(
                f"{what} does not fit this architecture: {key} has shape "
                f"{tuple(tensors[key].shape)}, expected {tuple(value.shape)}"
            )
    module.load_state_dict(dict(tensors))


def optimizer_to_tensors(optimizer: torch.optim.Optimizer, prefix: str) -> dict[str, torch.Tensor]:
    """An optimizer's per-parameter state as flat tensors (its hyperparameters live in the
    config, so only the moving state is kept)."""
    out = {}
    for index, state in optimizer.state_dict()["state"].items():
        for name, value in state.items():
            out[f"{prefix}.{index}.{name}"] = torch.as_tensor(value)
    return out


def optimizer_from_tensors(
    optimizer: torch.optim.Optimizer, tensors: Mapping[str, torch.Tensor], prefix: str
) -> None:
    state_dict = optimizer.state_dict()
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        if key.startswith(prefix + "."):
            index, name = key[len(prefix) + 1 :].split(".", 1)
            state.setdefault(int(index), {})[name] = value
    state_dict["state"] = state
    optimizer.load_state_dict(state_dict)
