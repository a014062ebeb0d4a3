"""One option vocabulary across every command, read from the Typer app itself.

The truth is the list in commands/options.py's docstring: a short flag means one
long option everywhere, `--format` is always the output format (table, tsv, jsonl),
`--scan-format` always the scan format, and `--model`, `--db`, `--topk` always carry
`-m`, `-d`, `-k`.
"""

from __future__ import annotations

from collections import defaultdict

import pytest
import typer
from typer.testing import CliRunner

from disco_cli.cli import app

OUTPUT_FORMATS = {"table", "tsv", "jsonl"}
SCAN_FORMATS = {"kitti", "nclt", "npy", "pcd", "ply", "oxford"}  # readers.FORMATS
SHORT = {"-m": "--model", "-d": "--db", "-k": "--topk", "-o": "--output"}


def _options() -> list[tuple[str, object]]:
    group = typer.main.get_command(app)
    out = []
    for name, cmd in sorted(group.commands.items()):
        for p in cmd.params:
            if p.param_type_name == "option":
                out.append((name, p))
    return out


def _choices(param: object) -> set[str]:
    """The values a choice option accepts, as the app's own type descriptor says."""
    desc = param.type_descriptor  # type: ignore[attr-defined]
    if not desc.is_choice:
        return set()
    return {getattr(c, "value", c) for c in desc.choices or ()}


def test_the_walk_sees_every_command() -> None:
    names = {name for name, _ in _options()}
    assert {"bev", "build-db", "query", "loops", "eval", "eval-loops", "gt-loops", "info"} <= names


def test_a_short_flag_means_one_option_everywhere() -> None:
    meaning: dict[str, set[str]] = defaultdict(set)
    for _, p in _options():
        longs = [o for o in p.opts if o.startswith("--")]
        for o in p.opts:
            if not o.startswith("--"):
                meaning[o].update(longs)
    bad = {flag: sorted(longs) for flag, longs in meaning.items() if len(longs) != 1}
    assert not bad, f"short flags with several meanings: {bad}"
    for flag, long in SHORT.items():
        assert meaning[flag] == {long}, flag


@pytest.mark.parametrize("long", sorted(SHORT.values()))
def test_the_common_options_always_have_their_short_flag(long: str) -> None:
    short = {v: k for k, v in SHORT.items()}[long]
    seen = [(name, p.opts) for name, p in _options() if long in p.opts]
    assert seen
    for name, opts in seen:
        assert short in opts, f"{name}: {long} without {short}"


def test_format_is_the_output_format_and_scan_format_the_input() -> None:
    fmt, scan = [], []
    for name, p in _options():
        if "--format" in p.opts or "-f" in p.opts:
            fmt.append(name)
            assert p.opts == ["--format"], f"{name}: {p.opts}"
            assert _choices(p) == OUTPUT_FORMATS, f"{name}: --format takes {_choices(p)}"
        if "--scan-format" in p.opts:
            scan.append(name)
            assert _choices(p) == SCAN_FORMATS, f"{name}: --scan-format takes {_choices(p)}"
        # No other option offers the output or the scan formats under another name.
        if p.opts[0] not in ("--format", "--scan-format"):
            assert not (_choices(p) & (OUTPUT_FORMATS | SCAN_FORMATS)), f"{name}: {p.opts}"
    # Every command that writes result rows takes --format; every one reading scans --scan-format.
    assert set(fmt) == {"query", "loops", "eval", "eval-loops", "gt-loops", "info"}
    assert set(scan) >= {"bev", "build-db", "query", "loops", "eval", "eval-loops"}


def test_calib_takes_a_file_everywhere() -> None:
    for name, p in _options():
        if "--calib" in p.opts:
            assert not p.is_flag and not p.secondary_opts, f"{name}: --calib is a flag"


def test_bev_takes_scan_format_and_bev_mode(tmp_path) -> None:
    import numpy as np

    from disco_cli.model.bev import BEVConfig, polar_bev

    rng = np.random.default_rng(0)
    # 1,500 points: a .bin is read as a scan from 1,000 (io/readers/plausible.py)
    pts = np.c_[rng.uniform(-30, 30, (1500, 2)), rng.uniform(-1, 3, 1500), rng.random(1500)]
    scan = tmp_path / "scan.dat"  # an extension that says nothing: --scan-format decides
    pts.astype(np.float32).tofile(scan)
    out = tmp_path / "bev.npy"
    args = ["bev", str(scan), "-o", str(out), "--scan-format", "kitti", "--bev-mode", "density"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    want = polar_bev(pts.astype(np.float32), BEVConfig(mode="density"))
    np.testing.assert_array_equal(np.load(out), want)
    # The old spelling of the scan format is refused rather than taken as an output format.
    res = CliRunner().invoke(app, ["bev", str(scan), "-o", str(out), "--format", "kitti"])
    assert res.exit_code == 2


def test_gt_loops_calib_file_and_none(tmp_path) -> None:
    import json

    import numpy as np

    seq = tmp_path / "seq"
    seq.mkdir()
    # Camera-frame poses (KITTI: x right, y down, z ahead): out along z and back; the
    # last frame is back at frame 0's place, turned 90 degrees about the camera's y.
    lines = []
    for i in range(61):
        z = float(i if i <= 30 else 60 - i)
        a = np.radians(90.0) if i == 60 else 0.0
        c, s = np.cos(a), np.sin(a)
        lines.append(f"{c} 0 {s} 0 0 1 0 0 {-s} 0 {c} {z}\n")
    (seq / "poses.txt").write_text("".join(lines))
    # LiDAR x (ahead) is camera z, LiDAR y (left) is camera -x, LiDAR z (up) camera -y.
    calib = "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n"
    (seq / "calib.txt").write_text(calib)
    elsewhere = tmp_path / "calib_copy.txt"
    elsewhere.write_text(calib)

    def yaw_60_0(*extra: str) -> float:
        res = CliRunner().invoke(app, ["gt-loops", str(seq), "--format", "jsonl", *extra])
        assert res.exit_code == 0, res.output
        rows = [json.loads(line) for line in res.stdout.splitlines()]
        return next(r["yaw_deg"] for r in rows if (r["query"], r["match"]) == (60, 0))

    # With the calib, the turn about the camera's vertical axis is a LiDAR yaw of 90
    # degrees; read as LiDAR poses (none), it is a roll that leaves the yaw at 0.
    assert abs(abs(yaw_60_0()) - 90.0) < 1e-6
    assert abs(abs(yaw_60_0("--calib", str(elsewhere))) - 90.0) < 1e-6
    assert abs(yaw_60_0("--calib", "none")) < 1e-6
    res = CliRunner().invoke(app, ["gt-loops", str(seq), "--calib", str(tmp_path / "no.txt")])
    assert res.exit_code == 1 and "no.txt" in res.stderr
    res = CliRunner().invoke(app, ["gt-loops", str(seq), "--no-calib"])
    assert res.exit_code == 2


# -- one vocabulary: the same idea under one name, with one type and range ---------------

# Names that must never both be offered: the same idea spelled twice. Each pair is
# (the name kept, the name that must not come back as a visible option).
SYNONYMS = [
    ("--max-distance", "--threshold"),  # the distance cut of query and loops
    ("--poses", "--query-poses"),  # the poses of the scans given on the command line
    ("--threads", "--workers"),  # how many threads a command computes with
]


def _visible() -> list[tuple[str, object]]:
    return [(name, p) for name, p in _options() if not p.hidden]


def _shape(param: object) -> tuple:
    """What a user sees of an option apart from its help: type, range, metavar, flagness."""
    p = param
    return (
        p.type_descriptor.annotation if not p.is_flag else bool,  # type: ignore[attr-defined]
        p.min,  # type: ignore[attr-defined]
        p.max,  # type: ignore[attr-defined]
        p.metavar,  # type: ignore[attr-defined]
        p.is_flag,  # type: ignore[attr-defined]
        p.multiple,  # type: ignore[attr-defined]
    )


def _plain_type(annotation: object) -> object:
    """Optional[X] and X are the same option type (one has no default)."""
    from typing import Union, get_args, get_origin

    if get_origin(annotation) in (Union, __import__("types").UnionType):
        args = [a for a in get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return annotation


def test_one_name_has_one_type_range_and_metavar_everywhere() -> None:
    shapes: dict[str, dict[tuple, list[str]]] = defaultdict(lambda: defaultdict(list))
    for name, p in _visible():
        long = next(o for o in p.opts if o.startswith("--"))
        shape = _shape(p)
        shapes[long][(_plain_type(shape[0]), *shape[1:])].append(name)
    bad = {long: dict(seen) for long, seen in shapes.items() if len(seen) > 1}
    assert not bad, f"options whose type, range or metavar differ between commands: {bad}"


@pytest.mark.parametrize(("kept", "gone"), SYNONYMS)
def test_one_idea_is_never_offered_under_two_names(kept: str, gone: str) -> None:
    offering = sorted({name for name, p in _visible() if gone in p.opts + p.secondary_opts})
    assert not offering, f"{gone} is offered by {offering}; the vocabulary's name is {kept}"


def test_boolean_options_are_flags() -> None:
    for name, p in _options():
        if _plain_type(p.type_descriptor.annotation) is bool:
            assert p.is_flag, f"{name}: {p.opts} takes a value instead of being a flag"


def _help(command: str, columns: int = 80) -> str:
    res = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": str(columns)})
    assert res.exit_code == 0, res.output
    return res.stdout


@pytest.mark.parametrize("command", sorted(typer.main.get_command(app).commands))  # type: ignore[attr-defined]
def test_help_at_80_columns_shows_every_option_whole_and_flags_as_flags(command: str) -> None:
    import re

    text = _help(command)
    assert max(len(line) for line in text.splitlines()) <= 80
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    for p in cmd.params:
        if p.param_type_name != "option" or p.hidden:
            continue
        for o in p.opts + p.secondary_opts:
            assert re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", text), (
                f"{command} --help at 80 columns does not show {o} whole"
            )
    # A flag takes no value, and its help must not say it does.
    assert "<bool>" not in text and "BOOLEAN" not in text, f"{command}: a flag shown with a value"


# -- usage errors: one line that names the option and where the help is ------------------


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["query", "scan.bin", "--topk", "0"],
            "disco query: --topk: 0 is not in the range 1<=x<=10000 (see disco query --help)",
        ),
        (
            ["loops", "seq", "--max-distance", "-1"],
            "disco loops: --max-distance: -1 is not in the range x>=0.0 (see disco loops --help)",
        ),
        (
            ["build-db", "seq", "--scan-format", "las"],
            "disco build-db: --scan-format: 'las' is not one of 'kitti', 'nclt', 'oxford', "
            "'npy', 'pcd', 'ply' (see disco build-db --help)",
        ),
        (["query"], "disco query: missing argument SCANS (see disco query --help)"),
        (["bev", "scan.bin"], "disco bev: missing option --output (see disco bev --help)"),
        (
            ["info", "map.db", "--chek"],
            "disco info: no such option --chek (did you mean --check or --help?) "
            "(see disco info --help)",
        ),
        (["train", "-o"], "disco train: option '-o' requires an argument (see disco train --help)"),
    ],
)
def test_a_usage_error_is_one_line_naming_the_option(args: list[str], line: str) -> None:
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2
    assert res.stderr.splitlines() == [f"error: {line}"]
    assert res.stdout == ""
