"""Executed docs: every fenced block of README.md and docs/**/*.md runs, or says why not.

Blocks, by the language after the fence:
- ```console: `$ ` lines are commands (a trailing `\\` continues one); the lines after a
  command are its output (stdout and stderr together), compared with what it prints.
  An output line `...` stands for any number of lines; a line ending in ` ...` for any
  line that starts with what precedes it (word by word). A table drawn with box
  characters is compared with what the command prints on a terminal. A command must
  exit with status 0, unless its output shows an error (a line starting `error:` or
  `Usage:`): then it must fail.
- ```sh: runs as one bash script (errexit, pipefail); its output is not compared.
- ```python: runs with the interpreter that runs this check; a ```text block right after
  it is its expected stdout.
- ```text, ```toml, ```json: not run (synopses, layouts, file contents).
A block without a language is an error: say what it is.

Each page runs in order in a scratch folder of its own holding data/samples (a link),
with `disco` and `python` on PATH for this interpreter, and no progress lines (they
depend on the machine's speed: `DISCO_PROGRESS_SECONDS` is set to a day). Numbers in
output are compared within a tolerance: at least 1.5 units of the last digit the page
prints (4 decimals at most) or 1e-3 of the value; angles (-180..180) compare around
the circle. Timings (`0.2 s`, `130.9 scans/s`, `3 ms`) are masked on both sides.

Marks, as an HTML comment in the prose right above a block:
- `<!-- docs-check: skip -->`: not run; the prose above must then say so to a reader
  on a line starting "Not run in CI:" with the reason. Its `disco` command lines are
  still checked against the CLI (the subcommand and every option exist), and python
  blocks compile.
- `<!-- docs-check: skip-all -->` anywhere in a page: every block of it, as skip (one
  "Not run in CI:" line on the page says why).
- `<!-- docs-check: tol=0.01 atol=0.05 -->`: relative and absolute tolerances.
- `<!-- docs-check: needs=kiss_icp -->`: run only where that module imports.
- `<!-- docs-check: timeout=600 -->`: seconds for the block (default 300).
`disco` command lines in every block (synopses too) are checked against the CLI, and
every relative link and #anchor must resolve.

Run: `python tests/docs_check.py [PAGE...]` (what `make docs-check` does), or
`python tests/docs_check.py --update [PAGE...]` to rewrite the outputs shown in the
pages from what the commands print now (lines that still match are kept as they are,
so timings and digits within tolerance do not churn). tests/test_docs_executed.py runs
the same check in the test suite.
"""

from __future__ import annotations

import argparse
import os
import pty
import re
import select
import shlex
import subprocess
import sys
import tempfile
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "data" / "samples"
LANGUAGES = {"console", "sh", "python", "text", "toml", "json"}
DEFAULT_TIMEOUT = 300


def pages() -> list[Path]:
    docs = sorted((REPO / "docs").rglob("*.md"))
    return [REPO / "README.md", *docs]


# ---------------------------------------------------------------------------- parsing

_FENCE = re.compile(r"^\s*```(\S*)\s*$")  # fences in list items are indented
_MARK = re.compile(r"<!--\s*docs-check:(.*?)-->")
_NOT_RUN = re.compile(r"^[*_]*Not run in CI:\s*(.+)")


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    end: int  # 1-based line of the closing fence
    lang: str
    text: str
    marks: dict[str, str] = field(default_factory=dict)
    not_run_line: str | None = None  # the reader's "Not run in CI: ..." line
    output: Block | None = None  # a python block's expected-output text block
    is_output: bool = False
    indent: str = ""  # a fence inside a list item is indented

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(REPO)}:{self.line}"

    @property
    def skipped(self) -> bool:
        return "skip" in self.marks


def parse_marks(text: str) -> dict[str, str]:
    marks: dict[str, str] = {}
    for m in _MARK.finditer(text):
        for word in m.group(1).split():
            key, _, value = word.partition("=")
            marks[key] = value
    return marks


def parse_page(path: Path) -> list[Block]:
    lines = path.read_text().splitlines()
    blocks: list[Block] = []
    prose: list[str] = []  # the lines since the last block
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            prose.append(lines[i])
            i += 1
            continue
        j = i + 1
        while j < len(lines) and not lines[j].lstrip().startswith("```"):
            j += 1
        prose_text = "\n".join(prose)
        block = Block(
            page=path,
            line=i + 1,
            end=j + 1,
            lang=m.group(1),
            text=textwrap.dedent("\n".join(lines[i + 1 : j])) + ("\n" if j > i + 1 else ""),
            marks=parse_marks(prose_text),
            indent=lines[i][: len(lines[i]) - len(lines[i].lstrip())],
        )
        for p in prose:
            n = _NOT_RUN.match(p.strip())
            if n:
                block.not_run_line = n.group(1)
        previous = blocks[-1] if blocks else None
        if (
            block.lang == "text"
            and previous is not None
            and previous.lang == "python"
            and not prose_text.strip()
        ):
            previous.output = block
            block.is_output = True
        blocks.append(block)
        prose = []
        i = j + 1
    # a page of commands that all need what CI lacks (the benchmarks) says so once
    if "skip-all" in parse_marks("\n".join(lines)):
        reason = next((n.group(1) for n in map(_NOT_RUN.match, lines) if n), None)
        for block in blocks:
            block.marks["skip"] = ""
            block.not_run_line = block.not_run_line or reason
    return blocks


def parse_console(text: str) -> list[tuple[str, list[str]]]:
    """A console block as (command, expected output lines) pairs."""
    steps: list[tuple[str, list[str]]] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("$ "):
            command = line[2:]
            while command.endswith("\\") and i + 1 < len(lines):
                i += 1
                command = command[:-1] + "\n" + lines[i]
            steps.append((command, []))
        elif steps:
            steps[-1][1].append(line)
        i += 1
    return steps


# ---------------------------------------------------------------------- comparison

# A number stands alone: the digits of 000004.bin or s00.db are text, compared exactly.
_NUMBER = re.compile(
    r"(?<![\w.])-?\d+(?:\.\d*(?![A-DF-Za-df-z_]))?(?:[eE][-+]?\d+)?(?![A-DF-Za-df-z_\d/])"
)
# A figure followed by a unit of time or of rate is a timing: masked on both sides.
_TIMING = re.compile(r"\d+(?:\.\d+)?\s?(?:ms|s|min|h|us|µs)\b|\d+(?:\.\d+)?\s?[\w-]+/s\b")
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


def mask_timings(line: str) -> str:
    return _TIMING.sub("<time>", line)


def _skeleton(line: str) -> str:
    text = _NUMBER.sub("#", mask_timings(line))
    return re.sub(r"\s+", " ", text).replace("[ ", "[").replace(" ]", "]").strip()


def _number_ok(got: str, want: str, rtol: float, atol: float | None) -> bool:
    if not re.search(r"[.eE]", want):  # indices and counts: exact
        return got.lstrip("-") == want.lstrip("-") and (got == want or int(want) == 0)
    a, b = float(got), float(want)
    digits = len(want.split(".")[1]) if "." in want and not re.search("[eE]", want) else 4
    tol = max(1.5 * 10.0 ** -min(digits, 4), rtol * abs(b), atol or 0.0)
    d = abs(a - b)
    if d > 180 and abs(a) <= 180 and abs(b) <= 180:  # angles: around the circle
        d = 360 - d
    return d <= tol


def line_matches(got: str, want: str, rtol: float = 1e-3, atol: float | None = None) -> bool:
    if want.endswith(" ..."):  # as many words as the page shows
        want = want[:-4]
        got = " ".join(got.split()[: len(want.split())])
    if _skeleton(got) != _skeleton(want):
        return False
    g_nums = _NUMBER.findall(mask_timings(got))
    w_nums = _NUMBER.findall(mask_timings(want))
    return all(_number_ok(a, b, rtol, atol) for a, b in zip(g_nums, w_nums))


def compare(got: str, want: list[str], rtol: float = 1e-3, atol: float | None = None) -> list[str]:
    """The differences between printed lines and documented ones (empty: they agree)."""
    got_lines = [line.rstrip() for line in got.strip("\n").splitlines()]
    want = [line.rstrip() for line in want]
    while want and not want[-1]:
        want = want[:-1]
    problems: list[str] = []
    g = 0
    for k, w in enumerate(want):
        if w == "...":
            nxt = next((x for x in want[k + 1 :] if x != "..."), None)
            if nxt is None:
                g = len(got_lines)
                continue
            while g < len(got_lines) and not line_matches(got_lines[g], nxt, rtol, atol):
                g += 1
            continue
        if g >= len(got_lines):
            problems.append(f"documented {w!r}, printed nothing more")
            return problems
        if not line_matches(got_lines[g], w, rtol, atol):
            problems.append(f"printed    {got_lines[g]!r}\n  documented {w!r}")
        g += 1
    if g < len(got_lines):
        problems.append(f"printed {len(got_lines) - g} more line(s): {got_lines[g]!r} ...")
    return problems


def updated_lines(got: str, want: list[str], rtol: float, atol: float | None) -> list[str]:
    """The documented lines rewritten from what was printed: a line that still matches
    is kept as written; `...` elisions and ` ...` truncations keep their shape."""
    got_lines = [line.rstrip() for line in got.strip("\n").splitlines()]
    if not compare(got, want, rtol, atol):
        return want
    if "..." in want:  # keep as many leading lines as the page showed, then elide
        head = want.index("...")
        got_lines = got_lines[:head] + (["..."] if len(got_lines) > head else [])
    out = []
    for k, g in enumerate(got_lines):
        w = want[k] if k < len(want) else None
        if w is not None and w.endswith(" ...") and len(g.split()) > len(w.split()) - 1:
            g = " ".join(g.split()[: len(w.split()) - 1]) + " ..."
        out.append(w if w is not None and line_matches(g, w, rtol, atol) else g)
    return out


# --------------------------------------------------------------- the CLI, without running

_SPLIT = re.compile(r"\s(?:\|\||\||;|&&|&)\s|;\s|\n|\$\(|\)")
_PREFIX_WORDS = {"do", "then", "else", "time", "exec", "!", "{", "("}


def _tokens(segment: str) -> list[str]:
    try:
        return shlex.split(segment, comments=True)
    except ValueError:
        return segment.split("#")[0].split()


def disco_invocations(text: str, console: bool) -> list[list[str]]:
    """Every `disco ...` command line of a block, as the words after `disco`."""
    if console:
        lines = [cmd for cmd, _ in parse_console(text)]
        text = "\n".join(lines)
    text = text.replace("\\\n", " ")
    found = []
    for segment in _SPLIT.split(text):
        words = _tokens(segment.replace("[", " ").replace("]", " "))
        i = 0
        while i < len(words) and (re.match(r"^\w+=", words[i]) or words[i] in _PREFIX_WORDS):
            i += 1
        if i < len(words) and words[i] == "disco":
            found.append(words[i + 1 :])
    return found


def _cli() -> object:
    import typer

    from disco_cli.cli import app

    return typer.main.get_command(app)


def _choices(param: object) -> set[str]:
    desc = getattr(param, "type_descriptor", None)
    if desc is None or not desc.is_choice:
        return set()
    return {str(getattr(c, "value", c)) for c in desc.choices or ()}


def check_invocation(words: list[str]) -> list[str]:
    """What is wrong with `disco WORDS` by the app's own options (empty: nothing)."""
    group = _cli()
    line = "disco " + " ".join(words)
    if not words or words[0].startswith("-"):
        cmd, rest = group, words
    elif words[0] in group.commands:  # type: ignore[attr-defined]
        cmd, rest = group.commands[words[0]], words[1:]  # type: ignore[attr-defined]
    else:
        return [f"{line!r}: no command {words[0]!r}"]
    options = {"--help": None}
    for p in cmd.params:  # type: ignore[attr-defined]
        if p.param_type_name == "option":
            for o in [*p.opts, *getattr(p, "secondary_opts", [])]:
                options[o] = p
    problems = []
    for k, word in enumerate(rest):
        if "$" in word or word in {"-", "--"} or re.match(r"^-\d", word):
            continue
        if not word.startswith("-") or word.startswith("-..."):
            continue
        names = word.split("=")[0].split("/")  # synopses: --residual/--no-residual
        for name in names:
            if name not in options:
                problems.append(f"{line!r}: {name} is not an option of this command")
                continue
            allowed = _choices(options[name])
            value = word.split("=", 1)[1] if "=" in word else None
            if value is None and k + 1 < len(rest) and allowed:
                value = rest[k + 1]
            if allowed and value is not None and "$" not in value and not value.isupper():
                bad = [v for v in value.split("|") if v not in allowed]
                if bad:
                    problems.append(f"{line!r}: {name} takes {sorted(allowed)}, not {bad}")
    return problems


# the benchmarks, and the research probes kept beside their notes
_BENCH = re.compile(
    r"(?<![\w/])((?:benchmarks|docs/research/probes)/[\w./-]+\.(?:py|sh))([^\n|;&]*)"
)


def check_scripts(text: str) -> list[str]:
    """Scripts of the repository that a block calls exist and know the options used."""
    problems = []
    for m in _BENCH.finditer(text.replace("\\\n", " ")):
        name, args = m.group(1), m.group(2).split("#")[0]
        while name:
            # A launcher (`as_avx2.py SCRIPT ARGS`) passes what follows the script on.
            inner = _BENCH.search(args)
            own = args[: inner.start()] if inner else args
            script = REPO / name
            if not script.is_file():
                problems.append(f"{name} does not exist")
                break
            source = script.read_text() + (REPO / "benchmarks" / "_common.py").read_text()
            for opt in re.findall(r"(?<![\w-])(--[\w-]+)", own):
                if f'"{opt}"' not in source and f"'{opt}'" not in source and opt not in source:
                    problems.append(f"{name}: no option {opt}")
            name, args = (inner.group(1), inner.group(2)) if inner else ("", "")
    return problems


# ----------------------------------------------------------------------------- links

_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    text = re.sub(r"<[^>]+>", "", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found: set[str] = set()
    counts: dict[str, int] = {}
    in_block = False
    for line in path.read_text().splitlines():
        if line.lstrip().startswith("```"):
            in_block = not in_block
        if in_block:
            continue
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(1))
            n = counts.get(base, 0)
            found.add(base if n == 0 else f"{base}-{n}")
            counts[base] = n + 1
        found.update(re.findall(r'<a (?:id|name)="([^"]+)"', line))
    return found


def check_links(path: Path) -> list[str]:
    problems = []
    in_block = False
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            in_block = not in_block
        if in_block:
            continue
        for target in _LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            where = f"{path.relative_to(REPO)}:{number}"
            if not dest.exists():
                problems.append(f"{where}: link to {target}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                problems.append(f"{where}: link to {target}: no such heading")
    return problems


# --------------------------------------------------------------------------- running


class Scratch:
    """A page's folder: data/samples, and `disco` and `python` for this interpreter."""

    def __init__(self, root: Path) -> None:
        self.root = root
        (root / "data").mkdir()
        (root / "data" / "samples").symlink_to(SAMPLES, target_is_directory=True)
        bin_dir = root.parent / "bin"
        bin_dir.mkdir(exist_ok=True)
        for name, args in (("disco", "-m disco_cli.cli"), ("python", ""), ("python3", "")):
            shim = bin_dir / name
            shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" {args} "$@"\n')
            shim.chmod(0o755)
        self.env = dict(os.environ)
        self.env.update(
            PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
            PYTHONUNBUFFERED="1",
            COLUMNS="120",
            TERM="dumb",
            NO_COLOR="1",
            # progress lines come every few seconds where stderr is a pipe: how many
            # depends on the machine, so the pages show none
            DISCO_PROGRESS_SECONDS="86400",
        )
        src = str(REPO / "src")
        if (REPO / "src" / "disco_cli").is_dir() and src not in self.env.get("PYTHONPATH", ""):
            # a checkout's compiled core lies in src/ (worktrees); installs find theirs
            if any((REPO / "src" / "disco_cli").glob("_core*")):
                self.env["PYTHONPATH"] = os.pathsep.join(
                    [src, *filter(None, [self.env.get("PYTHONPATH")])]
                )

    def shell(self, command: str, timeout: float) -> tuple[int, str]:
        """Run COMMAND in bash; stdout and stderr together, in the order written."""
        proc = subprocess.run(
            ["bash", "-e", "-o", "pipefail", "-c", command],
            cwd=self.root,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            timeout=timeout,
        )
        return proc.returncode, proc.stdout

    def terminal(self, command: str, timeout: float) -> tuple[int, str]:
        """Run COMMAND with stdout on a terminal (for tables); stderr follows it."""
        master, slave = pty.openpty()
        proc = subprocess.Popen(
            ["bash", "-e", "-o", "pipefail", "-c", command],
            cwd=self.root,
            env=self.env,
            stdout=slave,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
        )
        os.close(slave)
        chunks = []
        while True:
            ready, _, _ = select.select([master], [], [], timeout)
            if not ready:
                proc.kill()
                raise subprocess.TimeoutExpired(command, timeout)
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the terminal's other end closed
                break
            if not data:
                break
            chunks.append(data)
        os.close(master)
        err = proc.stderr.read() if proc.stderr else b""
        code = proc.wait()
        out = b"".join(chunks).decode(errors="replace") + err.decode(errors="replace")
        return code, _ANSI.sub("", out).replace("\r", "")


@dataclass
class Result:
    problems: list[str] = field(default_factory=list)
    replacements: list[tuple[Block, str]] = field(default_factory=list)  # for --update
    skipped: list[str] = field(default_factory=list)  # blocks left out (needs=...)


def static_problems(block: Block) -> list[str]:
    """What can be checked without running: marks, languages, CLI options, scripts."""
    problems = []
    if block.lang not in LANGUAGES:
        problems.append(
            f"{block.where}: a block needs a language ({', '.join(sorted(LANGUAGES))}),"
            f" not {block.lang!r}"
        )
    if block.skipped and not block.not_run_line:
        problems.append(f"{block.where}: marked skip, but no 'Not run in CI: reason' line")
    if block.not_run_line and not block.skipped:
        problems.append(f"{block.where}: says 'Not run in CI' but has no skip mark")
    if block.lang in {"python", "toml", "json"}:
        if block.lang == "python":
            try:
                compile(block.text, block.where, "exec")
            except SyntaxError as exc:
                problems.append(f"{block.where}: python does not compile: {exc}")
        return problems
    for words in disco_invocations(block.text, console=block.lang == "console"):
        problems += [f"{block.where}: {p}" for p in check_invocation(words)]
    problems += [f"{block.where}: {p}" for p in check_scripts(block.text)]
    return problems


def _tolerances(block: Block) -> tuple[float, float | None]:
    rtol = float(block.marks.get("tol", 1e-3))
    atol = float(block.marks["atol"]) if "atol" in block.marks else None
    return rtol, atol


def run_block(block: Block, scratch: Scratch, result: Result) -> None:
    timeout = float(block.marks.get("timeout", DEFAULT_TIMEOUT))
    rtol, atol = _tolerances(block)
    where = block.where
    if block.lang == "sh":
        code, out = scratch.shell(block.text, timeout)
        if code != 0:
            result.problems.append(f"{where}: exit status {code}:\n{out[-3000:]}")
    elif block.lang == "console":
        new_lines: list[str] = []
        for command, want in parse_console(block.text):
            table = any(c in "".join(want) for c in "┏┃│")
            runner = scratch.terminal if table else scratch.shell
            code, out = runner(command, timeout)
            # an output that shows an error documents a failing command
            fails = any(line.startswith(("error:", "Usage:")) for line in want)
            if (code != 0) != fails:
                result.problems.append(f"{where}: `{command}` exit status {code}:\n{out[-3000:]}")
            problems = compare(out, want, rtol, atol)
            result.problems += [f"{where}: `{command}`:\n  {p}" for p in problems]
            shown = command.replace("\n", "\\\n")
            new_lines += [f"$ {shown}", *updated_lines(out, want, rtol, atol)]
        result.replacements.append((block, "\n".join(new_lines) + "\n"))
    elif block.lang == "python":
        proc = subprocess.run(
            [sys.executable, "-c", block.text],
            cwd=scratch.root,
            env=scratch.env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        if proc.returncode != 0:
            result.problems.append(
                f"{where}: python exit {proc.returncode}:\n{proc.stderr[-3000:]}"
            )
        if block.output is not None:
            want = block.output.text.splitlines()
            problems = compare(proc.stdout, want, rtol, atol)
            result.problems += [f"{where}: python output:\n  {p}" for p in problems]
            new = updated_lines(proc.stdout, want, rtol, atol)
            result.replacements.append((block.output, "\n".join(new) + "\n"))


def check_page(path: Path, run: bool = True) -> Result:
    result = Result()
    blocks = parse_page(path)
    for block in blocks:
        result.problems += static_problems(block)
    result.problems += check_links(path)
    runnable = [
        b
        for b in blocks
        if not b.skipped and not b.is_output and b.lang in {"sh", "console", "python"}
    ]
    if not run or not runnable:
        return result
    with tempfile.TemporaryDirectory(prefix="docs-check-") as tmp:
        root = Path(tmp) / "page"
        root.mkdir()
        scratch = Scratch(root)
        for block in runnable:
            need = block.marks.get("needs")
            if need:
                try:
                    __import__(need)
                except ImportError:
                    result.skipped.append(f"{block.where}: needs {need}")
                    continue
            try:
                run_block(block, scratch, result)
            except subprocess.TimeoutExpired:
                result.problems.append(f"{block.where}: ran past its timeout")
    return result


def rewrite(path: Path, replacements: list[tuple[Block, str]]) -> bool:
    lines = path.read_text().splitlines(keepends=True)
    changed = False
    for block, text in sorted(replacements, key=lambda r: -r[0].line):
        if text != block.text:
            lines[block.line : block.end - 1] = [textwrap.indent(text, block.indent)]
            changed = True
    if changed:
        path.write_text("".join(lines))
    return changed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("pages", nargs="*", type=Path, help="pages (default: all)")
    parser.add_argument("--update", action="store_true", help="rewrite the shown outputs")
    parser.add_argument("--static", action="store_true", help="check without running")
    args = parser.parse_args(argv)
    chosen = [p.resolve() for p in args.pages] or pages()
    failed = 0
    for path in chosen:
        result = check_page(path, run=not args.static)
        name = path.relative_to(REPO)
        for line in result.skipped:
            print(f"skipped {line}")
        if args.update and rewrite(path, result.replacements):
            print(f"{name}: outputs rewritten")
        if result.problems:
            failed += 1
            print(f"{name}: {len(result.problems)} problem(s)")
            for p in result.problems:
                print(f"  {p}")
        else:
            print(f"{name}: ok")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
