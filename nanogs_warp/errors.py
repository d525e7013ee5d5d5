"""The one exception type that user-facing code turns into a one-line message and exit code 2."""


class InputError(Exception):
    """Bad input or an impossible request: the message is shown to the user as one line."""


class NanogsWarning(UserWarning):
    """Something the user should know that does not stop the work (e.g. PLY elements dropped): the
    commands show it as one line on stderr."""


def printable(message: str) -> str:
    """``message`` with its control characters (a newline in a file's name) written as escapes, so
    that a line of output stays one line."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in message)
