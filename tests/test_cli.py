"""The command line as a whole: version check, lazy imports behind --help, help texts."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version

import pytest
from typer.testing import CliRunner

from disco_cli.cli import app

HEAVY = ("torch", "numpy", "scipy", "disco_cli._core")


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )


def test_version_reports_package_and_core() -> None:
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0
    from disco_cli import _core

    expected = version("disco-cli")
    assert result.output.strip() == f"disco {expected} (core {_core.__version__})"
    # The core is built from the same pyproject version.
    assert _core.__version__ == expected


def test_version_fails_clearly_when_the_core_cannot_load() -> None:
    # A None entry in sys.modules makes `import disco_cli._core` raise ImportError,
    # as a missing or broken extension would.
    proc = _python(
        "import sys; sys.modules['disco_cli._core'] = None\n"
        "sys.argv = ['disco', '--version']\n"
        "from disco_cli.cli import main; main()"
    )
    assert proc.returncode == 1
    assert "compiled core cannot load" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def _commands() -> list[str]:
    import typer.main

    return sorted(typer.main.get_command(app).commands)


def test_every_command_has_help() -> None:
    commands = _commands()
    assert {"build-db", "query", "loops", "info", "bev", "simulate", "train", "eval"} <= set(
        commands
    )
    runner = CliRunner()
    for name in commands:
        result = runner.invoke(app, [name, "--help"])
        assert result.exit_code == 0, name
        assert "Usage" in result.output, name


@pytest.mark.parametrize("argv", [["--help"], ["query", "--help"], ["build-db", "--help"]])
def test_help_imports_nothing_heavy(argv: list[str]) -> None:
    # `disco --help` stays fast because torch, numpy and the compiled core load only
    # inside the commands. Checked in a fresh interpreter.
    proc = _python(
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from disco_cli.cli import app\n"
        f"r = CliRunner().invoke(app, {argv!r})\n"
        "assert r.exit_code == 0, r.output\n"
        f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
