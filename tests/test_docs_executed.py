"""Every page of the documentation runs as written (tests/docs_check.py says how): one
test per page, its blocks in order in a scratch folder, outputs compared with the page.
After a change that moves outputs: `python tests/docs_check.py --update PAGE`."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import docs_check  # noqa: E402

PAGES = docs_check.pages()


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(docs_check.REPO)) for p in PAGES])
def test_page_runs_as_written(page: Path, samples: Path) -> None:
    result = docs_check.check_page(page)
    assert not result.problems, "\n".join(result.problems)
    for line in result.skipped:
        print("skipped", line)


# The checker itself, on hand-made pages and outputs whose verdict is known.


def test_numbers_compare_within_the_printed_precision() -> None:
    want = ["20\tdata/samples/00/velodyne/000020.bin\t0.4469\t-26.9976"]
    assert not docs_check.compare("20\tdata/samples/00/velodyne/000020.bin\t0.4470\t-26.9977", want)
    # a stale yaw, another file, another index: each is caught
    assert docs_check.compare("20\tdata/samples/00/velodyne/000020.bin\t0.4469\t-25.1434", want)
    assert docs_check.compare("20\tdata/samples/00/velodyne/000021.bin\t0.4469\t-26.9976", want)
    assert docs_check.compare("21\tdata/samples/00/velodyne/000020.bin\t0.4469\t-26.9976", want)
    assert docs_check.compare("20\tdata/samples/00/velodyne/000020.bin\t0.2307\t-26.9976", want)


def test_yaw_compares_around_the_circle() -> None:
    assert not docs_check.compare("yaw -179.9998", ["yaw 179.9999"])
    assert docs_check.compare("yaw 176.0531", ["yaw 179.9638"])
    assert docs_check.compare("yaw 176.0531", ["yaw -179.9638"])


def test_timings_are_masked_and_counts_are_not() -> None:
    want = ["map.db: wrote 26 scans in 0.2 s (130.9 scans/s)"]
    assert not docs_check.compare("map.db: wrote 26 scans in 2.3 s (11.2 scans/s)", want)
    assert docs_check.compare("map.db: wrote 25 scans in 0.2 s (130.9 scans/s)", want)


def test_elisions() -> None:
    want = ["header", "1 a", "...", "$ end"]
    assert not docs_check.compare("header\n1 a\n2 b\n3 c\n$ end", want)
    assert docs_check.compare("header\n1 a\n2 b\n3 c", want)
    assert not docs_check.compare("EDGE 0 20 2.476 -0.07 9 9", ["EDGE 0 20 2.476 ..."])
    assert docs_check.compare("EDGE 0 21 2.476 -0.07 9 9", ["EDGE 0 20 2.476 ..."])
    assert docs_check.compare("a\nb", ["a"])  # a line more than documented


def test_numpy_spacing_and_signed_zero() -> None:
    want = ["loop 72 -> 0: fitness 0.80, t [ 0.6  0.6 -0. ] m"]
    assert not docs_check.compare("loop 72 -> 0: fitness 0.81, t [0.6 0.6 0. ] m", want)
    assert docs_check.compare("loop 72 -> 0: fitness 0.90, t [0.6 0.6 0.] m", want)


def test_update_keeps_lines_that_match_and_rewrites_the_rest() -> None:
    want = ["wrote 26 scans in 0.2 s", "yaw 176.0531", "dist 0.5182"]
    got = "wrote 26 scans in 3.1 s\nyaw 179.9638\ndist 0.51825"
    assert docs_check.updated_lines(got, want, 1e-3, None) == [
        "wrote 26 scans in 0.2 s",
        "yaw 179.9638",
        "dist 0.5182",
    ]


def test_command_lines_are_checked_against_the_cli() -> None:
    text = "disco query a.bin --db map.db --topk 3 --no-such-option\nfind x | disco loops s -k 1"
    found = docs_check.disco_invocations(text, console=False)
    assert found == [
        ["query", "a.bin", "--db", "map.db", "--topk", "3", "--no-such-option"],
        ["loops", "s", "-k", "1"],
    ]
    problems = docs_check.check_invocation(found[0])
    assert len(problems) == 1 and "--no-such-option" in problems[0]
    assert not docs_check.check_invocation(found[1])
    assert docs_check.check_invocation(["no-such-command"])
    assert docs_check.check_invocation(["query", "x", "--format", "xml"])
    # a synopsis: brackets, alternatives, a value to fill in
    synopsis = "disco train DATA... -o model.pt [--epochs 10] [--residual/--no-residual]"
    (words,) = docs_check.disco_invocations(synopsis, console=False)
    assert not docs_check.check_invocation(words)


def test_a_skip_mark_must_be_visible(tmp_path: Path) -> None:
    page = tmp_path / "p.md"
    page.write_text("Text.\n<!-- docs-check: skip -->\n```sh\ndisco info x.db\n```\n")
    (block,) = docs_check.parse_page(page)
    block.page = docs_check.REPO / "p.md"  # for the message only
    assert any("Not run in CI" in p for p in docs_check.static_problems(block))
    page.write_text(
        "Not run in CI: needs x.db.\n<!-- docs-check: skip -->\n"
        "```sh\ndisco info x.db --bogus\n```\n"
    )
    (block,) = docs_check.parse_page(page)
    block.page = docs_check.REPO / "p.md"
    problems = docs_check.static_problems(block)
    assert len(problems) == 1 and "--bogus" in problems[0]


def test_links_and_anchors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(docs_check, "REPO", tmp_path)
    (tmp_path / "b.md").write_text("# Re-ranking the nearest (`verify.py`)\n## Same\n## Same\n")
    good = "[x](b.md#re-ranking-the-nearest-verifypy) [y](b.md#same-1) [z](#top)\n# Top\n"
    (tmp_path / "a.md").write_text(good)
    assert not docs_check.check_links(tmp_path / "a.md")
    (tmp_path / "a.md").write_text("[x](b.md#gone) [y](c.md)\n")
    assert len(docs_check.check_links(tmp_path / "a.md")) == 2


def test_numbers_with_exponents() -> None:
    want = ['{"a": 5.199204055732557e-05, "b": 0.3673160672187805, "id": 5}']
    assert not docs_check.compare(
        '{"a": 5.199203934214157e-05, "b": 0.36731618642807, "id": 5}', want
    )
    assert docs_check.compare('{"a": 5.199203934214157e-05, "b": 0.4334, "id": 5}', want)
    assert docs_check.compare('{"a": 7.2e-03, "b": 0.3673160672187805, "id": 5}', want)


def test_a_documented_error_must_fail(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    page = tmp_path / "p.md"
    page.write_text(
        "```console\n$ ls no-such-file-here\nerror: x\n$ echo fine\nfine\n"
        "$ true\nerror: documented, but nothing fails\n```\n"
    )
    monkeypatch.setattr(docs_check, "REPO", tmp_path)
    monkeypatch.setattr(docs_check, "SAMPLES", tmp_path)
    result = docs_check.check_page(page)
    exits = [p for p in result.problems if "exit status" in p]
    assert len(exits) == 1 and "`true`" in exits[0]
