"""The study script's record: the per-seed result files it copies print the same tables once the
run folders are gone (scripts/imagination_study.py --record)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def test_record_keeps_what_the_tables_read(tmp_path, load_script):
    study = load_script("imagination_study")
    setting = next(name for name, short in study.SHORT.items() if short == "s0")
    out, dest, budgets = tmp_path / "runs", tmp_path / "studies", (250, 500)
    jobs = study.jobs_of(setting, out, ["hard"], 3, budgets, "runs/vae-fast")
    for job in jobs:
        folder = Path(job.folder)
        folder.mkdir(parents=True)
        (folder / "agent.safetensors").write_bytes(b"not recorded")
        for budget in budgets:
            success = 0.1 * job.seed + budget / 1000
            result = {"task": "hard", "budget": budget, "seed": job.seed, "method": "baseline",
                      "success": success, "model_accuracy": None}  # fmt: skip
            (folder / f"evaluation-{budget:05d}.json").write_text(json.dumps(result))
    args = ([setting], out, ["hard"], 3, budgets, "runs/vae-fast")
    before = study.table(*args), study.iqm_table(*args)

    assert study.record(jobs, out, dest) == 6
    shutil.rmtree(out)
    after = study.table([setting], dest, *args[2:]), study.iqm_table([setting], dest, *args[2:])
    assert after == before
    assert "35.0 (10.0) [n=3]" in before[0] and "60.0 (10.0) [n=3]" in before[0]
    assert not list(dest.rglob("*.safetensors"))


def test_a_record_without_the_budgets_imagined_file_prints_a_dash(tmp_path, load_script):
    """A recorded augmented run holds imagined-NNNNN.json only for the budgets that were last
    when it ran; a table at another budget shows '-' there instead of asking for the agent."""
    study = load_script("imagination_study")
    setting = next(name for name, short in study.SHORT.items() if short == "s93")
    dest = tmp_path / "studies"
    (job,) = study.jobs_of(setting, dest, ["hard"], 1, (250,), "runs/vae-fast")
    folder = Path(job.folder)
    folder.mkdir(parents=True)
    result = {"task": "hard", "budget": 250, "seed": 0, "method": "augmented", "success": 0.1,
              "model_accuracy": None}  # fmt: skip
    (folder / "evaluation-00250.json").write_text(json.dumps(result))
    (folder / "imagined-02000.json").write_text(json.dumps({"state": 0.99}))

    assert study.imagined(job, 250) is None
    assert "10.0" in study.table([setting], dest, ["hard"], 1, (250,), "runs/vae-fast")
