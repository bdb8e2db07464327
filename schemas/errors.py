"""What stops a command: a user's mistake or a signal, each reaching the user as one line.

Shared by the four commands (`datagen`, `train`, `drive`, `experiment`): schemas/cli.py turns a
UserError into `PROG SUBCOMMAND: error: message` and exit status 2, a Ctrl-C into 130 and a
SIGTERM into 143. It lives here because `training` may import only `schemas`.
"""

from __future__ import annotations


class UserError(Exception):
    """A mistake in the user's input or environment: the command prints its first line and
    exits with 2 (never a traceback)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch scheduler, `timeout`), raised as KeyboardInterrupt so that one code path
    stops on either (schemas.cli.stop_on_sigterm)."""


class Stopped(KeyboardInterrupt):
    """A stop (Ctrl-C or SIGTERM) the command has described itself, e.g. how much was done and
    how to resume: the runner prints `PROG SUBCOMMAND: message` and exits with 143 if `sigterm`,
    else 130."""

    def __init__(self, message: str, sigterm: bool = False):
        super().__init__(message)
        self.sigterm = sigterm
