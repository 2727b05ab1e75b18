"""A GPU check of the whole pipeline with the `fast` augmented agent's parts: a `smoke` study
on CUDA (V, then baseline and augmented populations with an ensemble of five MDNs, the mask
gate, the filtered belief, 2-step value expansion and Dyna rollouts from M_R, plans and the
generalization test), run again (nothing left to run, V read back), then `imagine evaluate`
on one augmented agent. The numbers of a `smoke` study mean nothing; what is checked is that
every step runs on the GPU and every table and figure is written.

    python scripts/gpu_smoke.py OUT

Through the Python API rather than the `imagine` command, so that it runs with whatever typer
a GPU machine has (the lent H200's Python 3.12 has PyTorch but not this package's pins).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from imagine.cli import evaluate_agent
from imagine.config import AGENT_PRESETS
from imagine.study.reproduce import StudyConfig, reproduce

FAST_AUGMENTED = {key: AGENT_PRESETS["fast"]["augmented"][key] for key in (
    "model_ensemble", "imagination_gate", "belief", "value_expansion", "imagination_from",
    "imagination_draw", "model_residual")}  # fmt: skip
"""The `fast` preset's own values of the parts checked, set on the `smoke` preset."""


def main() -> None:
    if len(sys.argv) != 2:
        raise SystemExit("usage: python scripts/gpu_smoke.py OUT")
    out = Path(sys.argv[1])
    config = StudyConfig(preset="smoke", tasks=("hard",), seeds=(0, 1), budgets=(150,),
                         overrides=FAST_AUGMENTED, device="cuda")  # fmt: skip
    start = time.perf_counter()
    _, failures = reproduce(config, out)
    print(f"study: {time.perf_counter() - start:.0f} s, failed runs: {failures or 'none'}")
    reproduce(config, out)  # resumed: nothing to run, V read back
    evaluate_agent(out / "runs" / "hard-augmented-0", episodes=200)


if __name__ == "__main__":
    main()
