"""Exceptions that carry a one-line message for the user (exit status 2)."""


class InputError(ValueError):
    """Bad input or arguments: the CLI prints the message on one line and exits 2."""
