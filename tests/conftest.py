"""Shared test settings: one torch thread per process (also for the `imagine` subprocesses),
so tests neither oversubscribe a 2-core machine nor slow each other down."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("IMAGINE_AUTO_DEVICE", "cpu")  # CPU arithmetic on a GPU machine too

import torch

torch.set_num_threads(1)
