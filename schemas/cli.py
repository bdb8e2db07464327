"""One runner for the four commands (`datagen`, `train`, `drive`, `experiment`).

    COMMANDS = (Command("fit", "train the model", add_fit, run_fit, resume=fit_hint), ...)
    def main(argv=None) -> int:
        return cli.main("train", __doc__, COMMANDS, argv)

A subcommand gets, for free: a one-line description in `PROG --help` and `PROG SUB --help`;
every flag's default appended to its help (`HelpFormatter`); a usage mistake as
`PROG SUB: error: message (see --help)` and exit status 2 (`Parser`); a UserError raised by its
`run` as `PROG SUB: error: message` and 2; Ctrl-C as `PROG SUB: interrupted` and 130, SIGTERM as
`PROG SUB: stopped (SIGTERM)` and 143 (128 + the signal, the shell's convention), each followed
by the command's resume hint where resuming works (`Command.resume`) or replaced by the
command's own account (schemas.errors.Stopped). Never a traceback for any of these.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from schemas.errors import Stopped, Terminated, UserError

INTERRUPTED = 128 + signal.SIGINT  # 130
TERMINATED = 128 + signal.SIGTERM  # 143
USER_ERROR = 2  # as argparse's usage errors


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs as written; a flag's default appended to its help unless the
    help already states it, or the default is None or False (a flag left out means "off" or
    "decided elsewhere", which its help says)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            not action.option_strings
            or default is None
            or default is False
            or default is argparse.SUPPRESS
            or default == []
            or "default" in text.lower()
        ):
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage mistake in one line: `PROG SUB: error: message`, exit 2."""

    def error(self, message: str):
        self.exit(USER_ERROR, f"{self.prog}: error: {message} (see --help)\n")


@dataclass(frozen=True)
class Command:
    """One subcommand.

    Attributes:
        name: as typed (`fit`).
        help: one line, shown in `PROG --help` and as `PROG NAME --help`'s description.
        add_arguments: adds the flags to the subcommand's parser.
        run: run(args) -> exit status (None: 0); raises UserError for a user's mistake.
        resume: resume(args) -> the hint printed after a stop (e.g. "run the same command
            again to resume"), None where there is nothing to resume.
        epilog: printed at the end of `PROG NAME --help`.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int | None]
    resume: Callable[[argparse.Namespace], str | None] | None = None
    epilog: str | None = None


def parser(prog: str, description: str, commands: Sequence[Command]) -> Parser:
    """The command's parser: one subparser per Command."""
    p = Parser(prog=prog, description=description, formatter_class=HelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for c in commands:
        if "\n" in c.help:
            raise ValueError(f"{prog} {c.name}: the help must be one line")
        s = sub.add_parser(
            c.name, help=c.help, description=c.help, epilog=c.epilog, formatter_class=HelpFormatter
        )
        c.add_arguments(s)
    return p


def main(
    prog: str, description: str, commands: Sequence[Command], argv: list[str] | None = None
) -> int:
    """Parse `argv` and run the subcommand it names; the exit status (module docstring)."""
    args = parser(prog, description, commands).parse_args(argv)
    command = next(c for c in commands if c.name == args.command)
    return run(f"{prog} {command.name}", command, args)


def run(where: str, command: Command, args: argparse.Namespace) -> int:
    """`command.run(args)` with UserError, Ctrl-C and SIGTERM turned into one line on stderr
    (prefixed `where`) and the exit status."""
    try:
        with stop_on_sigterm():
            return int(command.run(args) or 0)
    except UserError as e:
        status, message = USER_ERROR, f"error: {one_line(e)}"
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM as Terminated
        if isinstance(e, Stopped):
            sigterm, message = e.sigterm, str(e)
        else:
            sigterm = isinstance(e, Terminated) or sigterm_received()
            message = "stopped (SIGTERM)" if sigterm else "interrupted"
            hint = _resume_hint(command, args)
            if hint:
                message += f"; {hint}"
        status = TERMINATED if sigterm else INTERRUPTED
    # Printed once the exception is gone: the stopped command's frames, and the progress bars
    # they hold (which draw a last line when freed), go first, so this line is the last.
    gc.collect()
    sys.stderr.flush()
    print(f"{where}: {message}", file=sys.stderr)
    return status


def _resume_hint(command: Command, args: argparse.Namespace) -> str | None:
    if command.resume is None:
        return None
    try:
        return command.resume(args)
    except Exception:  # a hint must never turn a clean stop into a traceback
        return None


def one_line(e: BaseException) -> str:
    """An exception's message on one line (its lines joined), or its type's name if empty."""
    text = " ".join(line.strip() for line in str(e).splitlines() if line.strip())
    return text or type(e).__name__


# --------------------------------------------------------------------------------------------
# SIGTERM as KeyboardInterrupt

_sigterm_received = False


def sigterm_received() -> bool:
    """Whether SIGTERM arrived in the current stop_on_sigterm block (Ray's calls re-raise a
    KeyboardInterrupt of their own, so the exception's type alone does not tell)."""
    return _sigterm_received


@contextlib.contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """Within the block, SIGTERM raises Terminated (a KeyboardInterrupt) in the main thread;
    a second SIGTERM while stopping is ignored so that the clean-up finishes. Blocks nest (the
    runner's around a command's own); outside the main thread signals are left alone."""
    global _sigterm_received
    _sigterm_received = False

    def handler(signum, frame):
        global _sigterm_received
        _sigterm_received = True
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
