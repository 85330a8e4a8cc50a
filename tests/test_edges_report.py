"""experiments.edges_report: a page keeps the sections of runs no longer on this machine."""

from __future__ import annotations

import pytest

from experiments.edges_report import write_page, written_sections

PAGE = """# Benchmarks: edge cohorts

intro

## old-run: seeds 1, 2

Its figures, as written.

### Per class (pooled)

| a | b |

## other: seeds 3

More.
"""


def test_a_folder_without_results_keeps_its_written_section(tmp_path):
    page = tmp_path / "edges.md"
    page.write_text(PAGE)
    assert list(written_sections(page)) == ["old-run", "other"]
    write_page([tmp_path / "results" / "old-run"], page)
    text = page.read_text()
    assert "## old-run: seeds 1, 2\n\nIts figures, as written.\n\n### Per class (pooled)" in text
    assert "## other" not in text  # only the folders given
    assert f"--results {tmp_path / 'results' / 'old-run'} --out {page}" in text


def test_a_folder_with_neither_results_nor_a_section_is_an_error(tmp_path):
    page = tmp_path / "edges.md"
    page.write_text(PAGE)
    with pytest.raises(FileNotFoundError, match=r"bench_edges.json does not exist .* no section"):
        write_page([tmp_path / "results" / "new-run"], page)
    assert page.read_text() == PAGE  # nothing written
