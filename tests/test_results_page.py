"""`make reproduce` regenerates docs/results.md from the study's REPORT.md and keeps the text
written by hand below its marker."""

from __future__ import annotations

from imagine.study.results_page import KEPT, results_page


def test_the_results_page_is_the_report_with_the_hand_written_part_kept(tmp_path):
    study, docs = tmp_path / "study", tmp_path / "docs"
    (study / "figures").mkdir(parents=True)
    (study / "REPORT.md").write_text(
        "# Reproduction\n\n## Table II\n\n| a |\n\n![s](figures/s.png)\n"
    )
    (study / "figures" / "s.png").write_bytes(b"png")
    docs.mkdir()
    page = docs / "results.md"
    page.write_text(f"# old\n\nold numbers\n\n{KEPT}\n\n## Reading\n\nours\n")
    text = results_page(study, page)
    assert "old numbers" not in text and "## Table II" in text and "# Reproduction" not in text
    assert text.endswith(f"{KEPT}\n\n## Reading\n\nours\n")
    assert "make reproduce" in text.splitlines()[2]
    assert (docs / "figures" / "s.png").read_bytes() == b"png"
