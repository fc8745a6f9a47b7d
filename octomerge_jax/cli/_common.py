"""Shared pieces of the subcommands."""

from __future__ import annotations


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code ``exit_code`` (default 1)."""

    def __init__(self, message: str, exit_code: int = 1):
        super().__init__(message)
        self.exit_code = exit_code
