"""Errors meant for people: the CLI prints them as one line (no traceback) and exits with code 2."""


class UserError(Exception):
    """Bad input or a missing prerequisite; the message names the problem and the fix."""
