"""The errors a user's input can cause.

:class:`UserError` is the one type the command line turns into a one-line message with exit
status 2: a bad config value, an unreadable clip, a run file that is not one, gains at which the
simulation blows up. Anything else that escapes a command is a bug and shows its traceback.
A ``UserError`` is a ``ValueError`` so that library callers catching ``ValueError`` keep working.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input from the user; the message names the file and the field."""


class ConfigError(UserError):
    """Invalid configuration; the message names the file and the field."""
