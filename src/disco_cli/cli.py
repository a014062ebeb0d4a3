"""The `disco` command line: one Typer app.

Each subcommand lives in `disco_cli/commands/<name>.py` and is registered below.
Command modules import only typer at module level; numpy, torch and the compiled
core are imported inside the command functions so that `disco --help` is instant.
"""

from __future__ import annotations

import signal
import sys


def _interrupted_while_loading(signum: int, frame: object) -> None:
    # Ctrl-C while the modules below load: Python would print a KeyboardInterrupt
    # traceback from deep inside an import, before main() can catch anything.
    sys.stderr.write("error: interrupted\n")
    raise SystemExit(130)


# Until the end of this module (where the previous handler comes back); only the main
# thread may set one (a program importing this module from another keeps its own).
try:
    _sigint_before = signal.signal(signal.SIGINT, _interrupted_while_loading)
except ValueError:
    _sigint_before = None

import os  # noqa: E402
from typing import Annotated  # noqa: E402

import typer  # noqa: E402

# from disco_cli.commands import <name>   (one import per command)
from disco_cli.commands import (  # noqa: E402
    bev,
    build_db,
    correct,
    eval_loops,
    evaluate,
    gt_loops,
    info,
    loops,
    query,
    serve,
    simulate,
    train,
)
from disco_cli.commands.usage import DiscoGroup  # noqa: E402

app = typer.Typer(
    name="disco",
    cls=DiscoGroup,  # one-line usage errors, old option names, flags shown as flags
    help="LiDAR loop closure: which place in my map is this scan, and how am I turned?",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

# -- registration: one line per command ------------------------------------
# app.command("<name>", rich_help_panel="...")(<name>.<function>)
app.command("simulate", rich_help_panel="Data")(simulate.simulate)
app.command("gt-loops", rich_help_panel="Data")(gt_loops.gt_loops)
app.command("build-db", rich_help_panel="Map")(build_db.build_db)
app.command("info", rich_help_panel="Map")(info.info)
app.command("query", rich_help_panel="Localize")(query.query)
app.command("loops", rich_help_panel="Localize")(loops.loops)
app.command("serve", rich_help_panel="Localize")(serve.serve)
app.command("correct", rich_help_panel="Localize")(correct.correct)
app.command("eval", rich_help_panel="Evaluate")(evaluate.evaluate)
app.command("eval-loops", rich_help_panel="Evaluate")(eval_loops.evaluate_loops)
app.command("bev", rich_help_panel="Inspect")(bev.bev)
app.command("train", rich_help_panel="Model")(train.train)


def _print_version(value: bool) -> None:
    if not value:
        return
    # deferred: __version__ reads importlib.metadata (50-150 ms); only --version needs it
    from disco_cli import __version__

    try:
        # deferred: a core that cannot load is reported here, not as a traceback at start-up
        from disco_cli import _core
    except ImportError as exc:
        typer.echo(
            f"disco {__version__}: the compiled core cannot load ({exc}); reinstall disco", err=True
        )
        raise typer.Exit(1) from None
    typer.echo(f"disco {__version__} (core {_core.__version__})")
    raise typer.Exit(0)


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            callback=_print_version,
            is_eager=True,
            help="Print the version and check the install.",
        ),
    ] = False,
) -> None:
    """LiDAR loop closure: which place in my map is this scan, and how am I turned?"""


def main() -> None:
    """Console entry point: clean exits on Ctrl-C and on a closed pipe (`| head`)."""
    try:
        app()
    except DiscoError as exc:  # commands catch these; this is the safety net
        error(str(exc))
        sys.exit(1)
    except KeyboardInterrupt:
        error("interrupted")
        sys.exit(130)
    except BrokenPipeError:
        # The reader went away (`disco query ... | head`): stop quietly.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(0)


from disco_cli.errors import DiscoError  # noqa: E402
from disco_cli.runtime.console import error  # noqa: E402

# Loaded: Ctrl-C is a KeyboardInterrupt again, which main() and the commands handle.
if _sigint_before is not None:
    signal.signal(signal.SIGINT, _sigint_before)

if __name__ == "__main__":
    main()
