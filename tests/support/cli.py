"""The `phd` command run in the test's process, as a user runs it."""

from __future__ import annotations

from phd_cli import main


def run(capsys, *argv) -> tuple[int, str, str]:
    """`phd ARGV...` (each argument made a string): exit code, stdout, stderr."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err
