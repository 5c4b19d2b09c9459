"""The CLI's entry point run in this process, as a test reads it."""

from __future__ import annotations

from services.cli import main


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``autotune ARGV`` (argparse's own exits included)."""
    try:
        code = main(list(argv))
    except SystemExit as stop:
        code = stop.code
    out = capsys.readouterr()
    return code, out.out, out.err
