"""Errors that carry a message meant for the user."""


class UserError(Exception):
    """Bad input (a config field, a pattern, a file): shown as one clear line, no traceback.

    Raise it before any expensive work starts, and name the offending field, pattern or file.
    """
