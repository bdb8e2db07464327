"""Errors that reach the user as one line and a non-zero exit (never a traceback)."""


class UserError(Exception):
    """A mistake in the user's input or environment: `train` prints it and exits with 2."""
