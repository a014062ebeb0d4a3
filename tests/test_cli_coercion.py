"""The command line's values read without Pydantic (commands/coercion.py, issue 41):
the same values as Typer's own coercion, for every option of every command, and a
query's options parsed without importing Pydantic at all."""

from __future__ import annotations

import subprocess
import sys
from enum import Enum
from pathlib import Path

import pytest
import typer.main

from disco_cli.cli import app
from disco_cli.commands import coercion

_typer_coercion = pytest.importorskip("typer._coercion")
if coercion.RuntimeParam is None:  # pragma: no cover - another Typer
    pytest.skip("this Typer has no typer._coercion.RuntimeParam", allow_module_level=True)

NUMBERS = [
    "0",
    "7",
    "-3",
    "007",
    "+5",
    " 5",
    "5 ",
    "5.0",
    "1e3",
    "1_000",
    "abc",
    "",
    "-0",
    "99999999999999999999",
    "0.5",
    "-2.5",
    ".5",
    "5.",
    "1e-3",
    "1E3",
    "2.5e+2",
    "inf",
    "nan",
    "-inf",
    "1e400",
    "0x10",
    "1,5",
    "4096",
    "4097",
    "10000",
    "10001",
    "256",
    "257",
    "0.001",
    "20.0",
    "20.5",
]


def _samples(annotation: object, tmp: Path) -> list[object]:
    if annotation is int or annotation is float:
        return [*NUMBERS, 0, 3, -1, 0.5, 2.0, True]
    if annotation is bool:
        return [True, False, "true", "0", ""]
    if annotation is str:
        return ["x", "", "a b", "ümlaut", 5]
    if annotation is Path:
        (tmp / "file.bin").write_bytes(b"")
        (tmp / "dir").mkdir(exist_ok=True)
        return [
            str(tmp / "file.bin"),
            str(tmp / "dir"),
            str(tmp / "missing.db"),
            str(tmp) + "//dir/",
            "./rel.db",
            "-",
            "",
            Path("map.db"),
            tmp / "file.bin",
        ]
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        values = [str(m.value) for m in annotation]
        return [*values, *(v.upper() for v in values), "bogus", "", *annotation]
    return []


def _outcome(call):
    try:
        out = call()
    except Exception as exc:  # Typer's BadParameter or a ValueError
        return ("raised", type(exc).__name__, str(getattr(exc, "message", exc)))
    return ("value", type(out), out)


def _commands():
    group = typer.main.get_command(app)
    return [("disco", group), *group.commands.items()]


def test_fast_values_equal_typers_own(tmp_path: Path) -> None:
    checked = declined = 0
    for name, command in _commands():
        ctx = typer.main._click.Context(command) if hasattr(typer.main, "_click") else None
        for param in command.params:
            desc = param.type_descriptor
            if desc.file_annotation is not None:
                continue
            leaf = desc.annotation
            is_list = getattr(leaf, "__origin__", None) is list
            if is_list:
                leaf = leaf.__args__[0]
            typer_rp = _typer_coercion.build_runtime_param(desc)
            for sample in [param.default, *_samples(leaf, tmp_path)]:
                value = (sample,) if is_list and sample is not None else sample
                if value is None:
                    continue
                fast = _outcome(
                    lambda v=value, d=desc, p=param, c=ctx: coercion.fast_value(
                        d.annotation, d.parameter_info, v, p, c
                    )
                )
                if fast[0] == "value" and fast[2] is coercion._DECLINE:
                    declined += 1
                    continue
                slow = _outcome(
                    lambda v=value, t=typer_rp, p=param, c=ctx: t._coerce_value(v, param=p, ctx=c)
                )
                assert fast == slow, (name, param.name, value)
                checked += 1
    assert checked > 200 and declined > 50, (checked, declined)


def test_every_parameter_gets_the_fast_path() -> None:
    for name, command in _commands():
        for param in command.params:
            if param.type_descriptor.file_annotation is None:
                assert isinstance(param._runtime_param, coercion.FastRuntimeParam), (
                    name,
                    param.name,
                )


def test_a_query_reads_its_options_without_pydantic(tmp_path: Path) -> None:
    # What a fresh `disco query` parses, given the usual options: Pydantic (75-95 ms of
    # start-up with Typer 0.29) must not load. Bad values still go through Typer.
    code = f"""
import sys
import typer.main
from disco_cli.cli import app
group = typer.main.get_command(app)
parent = group.make_context("disco", ["query"])
query = group.commands["query"]
args = ["a.bin", "b.bin", "--db", {str(tmp_path / "map.db")!r}, "--topk", "3",
        "--format", "tsv", "--max-distance", "0.5", "--threads", "1", "--pose"]
ctx = query.make_context("query", args, parent=parent)
assert ctx.params["topk"] == 3 and ctx.params["scans"] == ["a.bin", "b.bin"], ctx.params
print("pydantic" in sys.modules)
try:
    query.make_context("query", ["a.bin", "--topk", "zero"], parent=parent)
except Exception as exc:
    print(type(exc).__name__, "pydantic" in sys.modules)
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out[0] == "False", out
    assert out[1:] == ["BadParameter", "True"], out
