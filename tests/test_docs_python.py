"""docs/python.md runs as written: each ```python block is executed in a scratch folder
holding data/samples (as from the repository root), and what it prints is compared with
the ```text block after it, every number to the precision it is printed with."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "python.md"
_BLOCK = re.compile(r"```python\n(.*?)```\n(?:\n```text\n(.*?)```)?", re.S)
_NUMBER = re.compile(r"-?\d+(?:\.\d*)?(?:e[-+]?\d+)?")


def blocks() -> list[tuple[str, str | None]]:
    return [(m.group(1), m.group(2)) for m in _BLOCK.finditer(DOC.read_text())]


def _skeleton(line: str) -> str:
    text = _NUMBER.sub("#", line)
    return re.sub(r"\s+", " ", text).replace("[ ", "[").replace(" ]", "]").strip()


def same_output(got: str, want: str) -> list[str]:
    """The differences between printed and documented output: the text must match, and
    each number be within 1.5 units of its last printed digit (or 1%)."""
    problems = []
    got_lines, want_lines = got.strip().splitlines(), want.strip().splitlines()
    if len(got_lines) != len(want_lines):
        return [f"{len(got_lines)} lines printed, {len(want_lines)} documented:\n{got}"]
    for g, w in zip(got_lines, want_lines):
        if _skeleton(g) != _skeleton(w):
            problems.append(f"printed {g!r}, documented {w!r}")
            continue
        for a, b in zip(_NUMBER.findall(g), _NUMBER.findall(w)):
            digits = len(b.split(".")[1]) if "." in b and "e" not in b else 0
            if "." not in b and "e" not in b:
                ok = a == b  # indices, counts: exact
            else:
                tol = max(1.5 * 10.0**-digits, 0.01 * abs(float(b)))
                ok = abs(float(a) - float(b)) <= tol
            if not ok:
                problems.append(f"printed {g!r}, documented {w!r} ({a} vs {b})")
    return problems


def test_the_doc_has_its_examples() -> None:
    found = blocks()
    assert len(found) >= 4 and all(want for _, want in found)
    assert sum("kiss_icp" in code for code, _ in found) == 1


@pytest.mark.parametrize("index", range(len(blocks())))
def test_python_md_block_runs_as_written(index: int, samples: Path, tmp_path: Path) -> None:
    code, want = blocks()[index]
    if "kiss_icp" in code:
        pytest.importorskip("kiss_icp", reason="kiss-icp is not installed (disco[examples])")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "samples").symlink_to(samples, target_is_directory=True)
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=1500
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert want is not None
    problems = same_output(proc.stdout, want)
    assert not problems, "\n".join(problems)


def test_output_comparison_catches_differences() -> None:
    want = "loop 72 -> 0: fitness 0.80, t [ 0.6  0.6 -0. ] m"
    assert not same_output("loop 72 -> 0: fitness 0.81, t [0.6 0.6 0. ] m", want)
    assert same_output("loop 73 -> 0: fitness 0.80, t [0.6 0.6 0.] m", want)
    assert same_output("loop 72 -> 0: fitness 0.90, t [0.6 0.6 0.] m", want)
    assert same_output("loop 72 -> 0: fitness 0.80, t [0.6 0.6 0.] m\nmore", want)
