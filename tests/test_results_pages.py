"""The result pages state what their committed JSON holds (scripts/results.py)."""
from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("results_pages", ROOT / "scripts" / "results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


R = _script()


@pytest.fixture()
def copy(tmp_path):
    """docs/results without its images: the JSON and the pages."""
    dst = tmp_path / "results"
    shutil.copytree(R.RESULTS, dst, ignore=shutil.ignore_patterns("*.png", "*.html"))
    return dst


def test_committed_pages_equal_what_their_json_gives():
    pages = R.expected()
    names = {p.relative_to(R.RESULTS).as_posix() for p in pages}
    # the method pages, the demo and every committed bench report are generated
    assert {"demc.md", "rae.md", "lbf.md", "gradnet.md", "demo.md", "bench_heldout/results.md",
            "demo/results.md"} <= names
    assert R.stale() == [], "run: python scripts/results.py"


def test_every_renderer_is_on_a_page_and_every_block_is_filled():
    used = set()
    for page in R.RESULTS.rglob("*.md"):
        for m in R.BLOCK.finditer(page.read_text()):
            used.add(m["name"])
            assert m["body"].strip(), f"{page}: empty block {m['name']}"
    assert used == set(R.TABLES)


def _edit(path: Path, fn) -> None:
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def test_deleting_a_number_from_a_json_fails_the_check(copy):
    assert R.stale(copy) == []
    # a summary value behind a method page's table
    _edit(copy / "bench_heldout_demc" / "results.json", lambda d: d["summary"][0].pop("relmse"))
    with pytest.raises(R.PageError, match=r"demc\.md.*demc-heldout"):
        R.expected(copy)


def test_deleting_a_record_value_fails_the_bench_report(copy):
    _edit(copy / "demo" / "results.json", lambda d: d["records"][0].pop("ssim"))
    with pytest.raises(R.PageError, match="not a complete bench report"):
        R.expected(copy)


def test_a_changed_number_makes_its_page_stale(copy):
    def bump(d):
        d["summary"]["64"]["gradnet"]["relmse"] *= 1.5
    _edit(copy / "gradnet_eval.json", bump)
    assert [p.name for p in R.stale(copy)] == ["gradnet.md"]
    assert R.main(["--check", "--results", str(copy)]) == 1
    assert R.main(["--results", str(copy)]) == 0  # rewrites the page from its JSON
    assert R.stale(copy) == []


def test_a_null_or_missing_file_is_named(copy):
    _edit(copy / "network_speed.json", lambda d: d["methods"]["demc"].update(gflop=None))
    with pytest.raises(R.PageError, match="expected a finite number, found None"):
        R.expected(copy)
    (copy / "network_speed.json").unlink()
    with pytest.raises(R.PageError, match="network_speed.json: no such result file"):
        R.expected(copy)


def test_an_unknown_table_is_an_error(copy):
    (copy / "x.md").write_text("<!-- results: nope -->\n<!-- /results -->\n")
    with pytest.raises(R.PageError, match="unknown table 'nope'"):
        R.expected(copy)


def test_every_results_page_is_generated_from_json():
    pages = set(R.expected())
    hand = {R.RESULTS / p for p in R.HAND_WRITTEN}
    loose = [p for p in R.RESULTS.rglob("*.md") if p not in pages and p not in hand]
    assert loose == [], "a results page neither generated nor listed as hand-written"
    for page, (module, rel) in R.STUDIES.items():  # each study page beside its JSON
        assert (R.RESULTS / page).is_file() and (R.RESULTS / rel).is_file(), page


def test_a_study_page_follows_its_json(copy):
    def bump(d):
        d["methods"]["lbf"]["total_median"] *= 2
    _edit(copy / "lbf_timing.json", bump)
    assert sorted(p.name for p in R.stale(copy)) == ["lbf.md", "lbf_timing.md"]  # the study and the method page
