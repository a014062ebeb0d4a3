"""Option values read without Pydantic where that changes nothing (issue 41).

Typer 0.29 checks and converts every option's value through a Pydantic `TypeAdapter`
built when the value is first read. For `disco query` that is 24 adapters on every
run, and the first one imports Pydantic: 75-95 ms of a fresh process's start-up on a
2-core AMD EPYC, a third of the whole first answer (docs/benchmarks.md, "Start-up and
typer's releases").

Most of disco's values need none of it: a default that is already of its type, a
number written plainly, a string, a path, an enum member by its exact name. For
those `fast_value` gives what Typer's own coercion gives (tests/test_cli_coercion.py
compares the two over every option of every command); anything else (a range missed, a
malformed number, a choice in other case, a parser, a tuple) goes to Typer's own
coercion, built then, so its checks and error messages stay Typer's.

This reads three private names of Typer (`typer._coercion.RuntimeParam`,
`build_runtime_param`, `typer._param_types.coerce_cli_path`) and two attributes of its
parameters (`type_descriptor`, `_runtime_param`). Where a release lacks any of them,
`install` leaves the parameters alone: every value then goes through Typer as
released, slower but the same, and `benchmarks/check_startup.py` (run by `make test`)
fails on the time.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, get_args, get_origin

try:
    from typer._coercion import RuntimeParam, build_runtime_param
    from typer._param_types import coerce_cli_path
except ImportError:  # a Typer without them (before 0.29, or a later one): Typer as it is
    RuntimeParam = None  # type: ignore[assignment,misc]

_DECLINE = object()  # "not for the fast path": Typer's own coercion decides
_INT = re.compile(r"-?[0-9]{1,18}")
_FLOAT = re.compile(r"-?(?:[0-9]{1,30}(?:\.[0-9]{0,30})?|\.[0-9]{1,30})(?:[eE][-+]?[0-9]{1,3})?")


def _in_range(number: float, info: Any) -> bool:
    return (info.min is None or number >= info.min) and (info.max is None or number <= info.max)


def _leaf(annotation: Any, info: Any, value: Any, param: Any, ctx: Any) -> Any:
    """One value of a scalar type, or _DECLINE."""
    kind = type(value)
    if annotation is bool:
        return value if kind is bool else _DECLINE
    if annotation is str:
        return value if kind is str else _DECLINE
    if annotation is int or annotation is float:
        if kind is annotation:
            number = value
        elif annotation is float and kind is int:  # a default written `= 0`
            number = float(value)
        elif kind is str and (_INT if annotation is int else _FLOAT).fullmatch(value):
            number = annotation(value)
        else:
            return _DECLINE
        if annotation is float and not math.isfinite(number):
            return _DECLINE
        return number if _in_range(number, info) else _DECLINE
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        if kind is annotation:
            return value
        if kind is not str or not info.case_sensitive:
            return _DECLINE
        if ctx is not None and getattr(ctx, "token_normalize_func", None) is not None:
            return _DECLINE
        return next((m for m in annotation if str(m.value) == value), _DECLINE)
    if annotation is Path and info.path_type is None and not info.allow_dash:
        if isinstance(value, Path):  # a default: Typer checks it without Pydantic
            return coerce_cli_path(value, info, path_type=Path, param=param, ctx=ctx)
        if kind is not str or not value or "\0" in value:
            return _DECLINE
        # Typer's own path checks (exists, readable, ...) on the string as given, as
        # Typer makes them, so that its messages name what was typed; Typer converts
        # the string to a Path first, through Pydantic, which is all that is skipped.
        checked = coerce_cli_path(value, info, path_type=None, param=param, ctx=ctx)
        return checked if isinstance(checked, Path) else Path(checked)
    return _DECLINE


def fast_value(annotation: Any, info: Any, value: Any, param: Any = None, ctx: Any = None) -> Any:
    """`value` as Typer would coerce it for `annotation`, or _DECLINE."""
    if info.parser is not None:
        return _DECLINE
    if get_origin(annotation) is list:
        (item,) = get_args(annotation) or (Any,)
        if not isinstance(value, (list, tuple)):
            return _DECLINE
        out = [_leaf(item, info, v, param, ctx) for v in value]
        return _DECLINE if any(v is _DECLINE for v in out) else out
    return _leaf(annotation, info, value, param, ctx)


if RuntimeParam is not None:

    @dataclass(frozen=True)
    class FastRuntimeParam(RuntimeParam):
        """Typer's RuntimeParam: the fast path first, Typer's own coercion otherwise."""

        descriptor: Any = None
        _typer: list = field(default_factory=list)  # Typer's RuntimeParam, once built

        def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
            out = fast_value(self.annotation, self.parameter_info, value, param, ctx)
            if out is not _DECLINE:
                return out
            if not self._typer:
                self._typer.append(build_runtime_param(self.descriptor))
            return self._typer[0]._coerce_value(value, param=param, ctx=ctx)


def install(params: Any) -> int:
    """Give each of `params` the fast path; how many got it (0 on another Typer)."""
    if RuntimeParam is None:
        return 0
    done = 0
    for p in params:
        desc = getattr(p, "type_descriptor", None)
        if desc is None or getattr(p, "_runtime_param", _DECLINE) is not None:
            continue
        if getattr(desc, "file_annotation", None) is not None:
            continue  # Typer opens files itself, without Pydantic
        p._runtime_param = FastRuntimeParam(
            parameter_info=desc.parameter_info, annotation=desc.annotation, descriptor=desc
        )
        done += 1
    return done
