"""Where a recorded result came from: the resolved config, the commit and V's hash.

Every evaluation a study writes (``evaluation-NNNNN.json``) carries :func:`provenance`, so that
a number copied into the docs can be traced to the code and the V that made it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import subprocess
from pathlib import Path
from typing import Any

VAE_WEIGHTS = "vae.safetensors"
"""V's weights in a V run folder (what ``vae_sha256`` hashes)."""


@functools.cache
def commit() -> str:
    """The git commit of this checkout of imagine (``+dirty`` with uncommitted changes), or
    ``unknown`` outside a git checkout (an installed wheel)."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True,
                              text=True, check=True, timeout=10).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=here, capture_output=True, text=True, check=True,
                               timeout=10).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


@functools.cache
def file_sha256(path: str) -> str | None:
    """The SHA-256 of a file's bytes (None if it is not there)."""
    file = Path(path)
    if not file.is_file():
        return None
    digest = hashlib.sha256()
    with file.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def vae_sha256(vae_run: str | None) -> str | None:
    """The hash of V's weights in a V run folder (None: no V, e.g. the oracle encoder)."""
    return None if vae_run is None else file_sha256(str(Path(vae_run) / VAE_WEIGHTS))


def provenance(config: Any) -> dict[str, Any]:
    """The record of an agent config's result: the config itself, the commit, V's hash."""
    return {"config": dataclasses.asdict(config), "commit": commit(),
            "vae_sha256": vae_sha256(getattr(config, "vae_run", None))}  # fmt: skip
