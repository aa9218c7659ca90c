"""docs/benchmarks.md's numbers are the ones in the committed results files (benchmarks/results/).

benchmarks.page writes every number between ``<!-- bench:NAME -->`` markers from the results
JSON; a page edited by hand, or a results file rerun without regenerating the page, fails here.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from benchmarks import page as rt

REPO = Path(__file__).resolve().parent.parent
PAGE = REPO / "docs" / "benchmarks.md"


def test_page_matches_results_files(capsys):
    assert rt.main(["--check"]) == 0, capsys.readouterr().out


def test_every_block_is_on_the_page_once():
    text = PAGE.read_text()
    for name in rt.BLOCKS:
        assert text.count(f"<!-- bench:{name} -->") == 1, name
        assert text.count(f"<!-- /bench:{name} -->") == 1, name


def test_a_hand_edited_number_fails_the_check(tmp_path, capsys):
    text = PAGE.read_text()
    # the warp table's kornia row, as the results file gives it, changed by one digit
    row = next(line for line in text.splitlines() if line.startswith("| kornia `warp_frame"))
    cells = row.split(" | ")
    cells[1] = str(int(cells[1]) + 1)
    stale = tmp_path / "benchmarks.md"
    stale.write_text(text.replace(row, " | ".join(cells)))
    assert rt.main(["--check", "--page", str(stale)]) == 1
    assert "differ" in capsys.readouterr().err
    # regenerating puts the number from the results file back
    assert rt.main(["--page", str(stale)]) == 0
    assert stale.read_text() == text


def test_a_changed_results_file_fails_the_check(tmp_path):
    results = tmp_path / "results"
    shutil.copytree(REPO / "benchmarks" / "results", results)
    path = results / "store" / "store_bench.json"
    d = json.loads(path.read_text())
    d["lookup"][0]["octree_us_median"] = 1234.4  # written as "1234 us" in the store table
    path.write_text(json.dumps(d))
    new = rt.regenerate(PAGE.read_text(), results)
    assert "| 10^3 | 1234 us (59) | 72 us |" in new
    copy = tmp_path / "benchmarks.md"
    copy.write_text(PAGE.read_text())
    assert rt.main(["--check", "--page", str(copy), "--results", str(results)]) == 1


def test_markers_must_match_the_blocks():
    text = PAGE.read_text()
    with pytest.raises(rt.PageBlockError, match=r"missing \['warp'\]"):
        rt.regenerate(text.replace("<!-- bench:warp -->", "<!-- bench-warp -->"))
    with pytest.raises(rt.PageBlockError, match=r"unknown \['nope'\]"):
        rt.regenerate(text + "\n<!-- bench:nope -->\nx\n<!-- /bench:nope -->\n")


def test_span_formats_ranges():
    assert rt.span([84.26, 83.79]) == "84"
    assert rt.span([31.8, 37.0]) == "32-37"
    assert rt.span([0.494, 0.629], rt.f2) == "0.49-0.63"


def test_trace_time_error_claims_only_from_quiet_runs(tmp_path):
    """A time/error run whose 1-minute load at the start was >= 1 (or not recorded) is labelled
    and makes no claim (no bold 'met' cells, no prose); the same numbers from a quiet run do."""
    results = tmp_path / "results"
    shutil.copytree(REPO / "benchmarks" / "results", results)
    d = json.loads((results / "trace" / "time_error.json").read_text())
    d["results"]["scenes"] = {"cornell_box": d["results"]["scenes"]["cornell_box"]}

    def cornell_block(quiet: bool, load: float) -> str:
        d.update(quiet=quiet, load_average_start=[load, load, load])
        (results / "trace" / "time_error_cornell_box.json").write_text(json.dumps(d))
        block = rt.block_trace_time_error(results)
        return block[block.index("**Cornell box**") : block.index("**Sponza**")]

    loaded = cornell_block(False, 2.5)
    assert "time_error_cornell_box.json" in loaded and "not a quiet run: no claim" in loaded
    assert "**0." not in loaded and "quiet run: the RMSE target" not in loaded
    # a file that claims quiet but recorded a load >= 1 is not trusted either
    assert "not a quiet run" in cornell_block(True, 1.2)
    quiet = cornell_block(True, 0.4)
    assert "not a quiet run" not in quiet and "quiet run: the RMSE target is met" in quiet
    assert "**0." in quiet  # the ratios <= 0.5 are bold (met)


def test_every_block_has_an_owning_benchmark_that_it_names():
    """Each table belongs to one benchmark module (intro aside): the module exists, runs as
    ``python -m benchmarks.NAME`` and the block says which it is."""
    assert set(rt.OWNERS) == set(rt.BLOCKS) - {"intro"}
    for name, owner in rt.OWNERS.items():
        assert (REPO / "benchmarks" / f"{owner}.py").is_file(), (name, owner)
        assert f"benchmarks.{owner}" in rt.BLOCKS[name](rt.RESULTS), (name, owner)
