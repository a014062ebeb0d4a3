"""How the command line reads its options and reports their misuse.

- A usage error (a bad value, a missing or unknown option) is one line that names the
  option and points to the command's help, like every other disco error, instead of
  the rich box Typer draws.
- Old option names keep working for a while: `DEPRECATED` maps each to its new name;
  the old name is rewritten before parsing, with one warning line, and is not shown
  in the help.
- A flag shows as a flag in the help (Typer's rich help writes `<bool>` after it, as
  if it took a value).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import typer
from typer._click import exceptions as ce
from typer._click.utils import PacifyFlushWrapper
from typer.core import TyperCommand, TyperGroup

from disco_cli.commands import coercion
from disco_cli.runtime.console import error, stdout_closed, warn

# Old name -> new name (issue 26: one name per idea). Rewritten only in commands that
# have the new name and not the old one.
DEPRECATED = {
    "--threshold": "--max-distance",
    "-t": "--max-distance",
    "--query-poses": "--poses",
    "--workers": "--threads",
}


def _program(ctx: Any) -> str:
    """`disco` or `disco CMD`, whatever the interpreter called the program."""
    if ctx is None:
        return "disco"
    return "disco" if ctx.parent is None else f"disco {ctx.info_name}"


def _option_name(param: Any) -> str:
    if param.param_type_name == "option":
        return next((o for o in param.opts if o.startswith("--")), param.opts[0])
    return (param.metavar or param.name or "").upper()


def _bad_value(exc: Any) -> str:
    """What was wrong with the value, with the value itself."""
    cause = exc.__cause__
    errors = getattr(cause, "errors", None)
    detail = errors()[0] if callable(errors) and errors() else None
    param = exc.param
    if detail is not None:
        value = detail.get("input")
        limits = getattr(param, "_get_number_range_help_str", lambda: None)()
        if limits and detail.get("type", "").startswith(("greater", "less")):
            return f"{value} is not in the range {limits}"
        msg = str(detail.get("msg", exc.message)).removeprefix("Value error, ")
        msg = msg[:1].lower() + msg[1:]
        return msg if repr(value) in msg else f"{value!r}: {msg}"
    return str(exc.message)


def usage_line(exc: Any) -> str:
    """One line for a usage error: the program, the option, the problem, where help is."""
    ctx = getattr(exc, "ctx", None)
    prog = _program(ctx)
    param = getattr(exc, "param", None)
    if isinstance(exc, ce.MissingParameter) and param is not None:
        kind = "option" if param.param_type_name == "option" else "argument"
        text = f"missing {kind} {_option_name(param)}"
    elif isinstance(exc, ce.BadParameter) and param is not None:
        text = f"{_option_name(param)}: {_bad_value(exc)}"
    elif isinstance(exc, ce.NoSuchOption):
        text = f"no such option {exc.option_name}"
        if exc.possibilities:
            text += f" (did you mean {' or '.join(sorted(exc.possibilities))}?)"
    else:
        text = exc.format_message()
        text = text[:1].lower() + text[1:]
    text = " ".join(text.split())  # one line, whatever the message held
    return f"{prog}: {text.rstrip('.')} (see {prog} --help)"


def _renamed(command: Any, args: Sequence[str]) -> list[str]:
    """`args` with deprecated option names replaced by their new ones, one warning each."""
    have = {o for p in command.params for o in p.opts + p.secondary_opts}
    out: list[str] = []
    for i, arg in enumerate(args):
        if arg == "--":  # what follows is not options
            return out + list(args[i:])
        old, eq, value = arg.partition("=")
        new = DEPRECATED.get(old)
        if new is not None and new in have and old not in have:
            warn(f"{old} is now {new}; the old name will go")
            arg = new + eq + value
        out.append(arg)
    return out


def _flag_type(ctx: Any) -> None:
    """A flag's type in the help: none (it takes no value)."""
    return None


def _flags_as_flags(params: Sequence[Any]) -> None:
    for p in params:
        if p.param_type_name == "option" and getattr(p, "is_flag", False):
            p.display_type_rich = _flag_type


class DiscoCommand(TyperCommand):
    """A disco subcommand: deprecated names rewritten, flags shown as flags."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _flags_as_flags(self.params)
        coercion.install(self.params)

    def get_help_option(self, ctx: Any) -> Any:
        option = super().get_help_option(ctx)
        _flags_as_flags([option] if option is not None else [])
        coercion.install([option] if option is not None else [])
        return option

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        try:
            return super().parse_args(ctx, _renamed(self, args))
        except ce.UsageError as exc:  # the parser's own errors may come without their command
            exc.ctx = exc.ctx or ctx
            raise


class DiscoGroup(TyperGroup):
    """The `disco` group: usage errors as one line on stderr, exit status 2."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _flags_as_flags(self.params)
        coercion.install(self.params)
        # Every subcommand reads as a DiscoCommand, whoever registers it, so that
        # cli.py's registration lines stay plain `app.command(...)`.
        for command in self.commands.values():
            if type(command) is TyperCommand:
                command.__class__ = DiscoCommand
                _flags_as_flags(command.params)
            # Values read without Pydantic where that changes nothing (issue 41).
            coercion.install(command.params)

    def get_help_option(self, ctx: Any) -> Any:
        option = super().get_help_option(ctx)
        _flags_as_flags([option] if option is not None else [])
        coercion.install([option] if option is not None else [])
        return option

    def main(
        self,
        args: Sequence[str] | None = None,
        prog_name: str | None = None,
        complete_var: str | None = None,
        standalone_mode: bool = True,
        **extra: Any,
    ) -> Any:
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except SystemExit as exc:
            # On a closed stdout (`disco --help | head -1`) rich (printing the help) and
            # Typer exit 1: for us a reader that had enough is a normal end, exit 0.
            closed = isinstance(exc.__context__, BrokenPipeError)
            if exc.code == 1 and (closed or isinstance(sys.stdout, PacifyFlushWrapper)):
                raise SystemExit(stdout_closed().exit_code) from None
            raise
        except ce.NoArgsIsHelpError:
            sys.exit(2)  # the help is printed already
        except ce.ClickException as exc:
            error(usage_line(exc))
            sys.exit(exc.exit_code)
        except typer.Abort:
            error("aborted")
            sys.exit(1)
        # Not standalone, Typer returns an Exit's status, or the command's value (None).
        sys.exit(rv if isinstance(rv, int) and not isinstance(rv, bool) else 0)
