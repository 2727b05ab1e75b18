"""Shared test settings: one torch thread per process (also for the `imagine` subprocesses),
so tests neither oversubscribe a 2-core machine nor slow each other down."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("IMAGINE_AUTO_DEVICE", "cpu")  # CPU arithmetic on a GPU machine too

import torch

torch.set_num_threads(1)

import pytest  # noqa: E402


@pytest.fixture
def smoke_agent(tmp_path):
    """Train one `smoke` augmented agent (oracle encoder, 30 episodes, imagination from
    episode 10) with ``overrides``, save it, and return (its config, the agent loaded back)."""
    from imagine.config import agent_preset
    from imagine.learning.agent import load_agent
    from imagine.learning.training import train_population

    def train(**overrides):
        config = agent_preset("smoke", encoder="oracle", method="augmented", episodes=30,
                              imagination_start=10, log_every=10, checkpoint_every=10,
                              accuracy_every=10, **overrides)  # fmt: skip
        train_population([config], [tmp_path / "run"], threads=1)
        return config, load_agent(tmp_path / "run")

    return train


@pytest.fixture
def load_script():
    """Import one of `scripts/` by name (e.g. ``load_script("m_sample_bound")``), with the
    folder on the path while it loads, as it is when run (scripts import their siblings)."""
    import importlib.util
    import sys
    from pathlib import Path

    folder = Path(__file__).parents[1] / "scripts"

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.path.insert(0, str(folder))
        try:
            spec.loader.exec_module(module)
        finally:
            sys.path.remove(str(folder))
        return module

    return load
