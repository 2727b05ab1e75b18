"""scripts/gpu_smoke.py checks the `fast` augmented agent's parts with the preset's own values."""

from __future__ import annotations


def test_the_gpu_smoke_check_sets_the_fast_presets_own_values(load_script):
    from imagine.config import AGENT_PRESETS

    parts, fast = load_script("gpu_smoke").FAST_AUGMENTED, AGENT_PRESETS["fast"]["augmented"]
    assert parts["model_ensemble"] == fast["model_ensemble"] > 1
    assert parts["imagination_gate"] == fast["imagination_gate"] != "none"
    assert parts["belief"] == fast["belief"]
