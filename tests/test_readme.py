"""README.md's promises: at most 300 lines, and its Python snippet runs as written."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_is_one_screen_of_a_product_not_a_notebook():
    assert len(README.read_text().splitlines()) <= 300


def test_the_readmes_python_snippet_runs_as_written(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) == 1, "the README holds one Python snippet"
    monkeypatch.chdir(tmp_path)  # its run folders go here
    exec(compile(blocks[0], "README.md", "exec"), {"__name__": "readme"})
    assert (tmp_path / "runs" / "api-cartpole-agent").is_dir()
