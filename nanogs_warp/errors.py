"""The one exception type that user-facing code turns into a one-line message and exit code 2."""


class InputError(Exception):
    """Bad input or an impossible request: the message is shown to the user as one line."""
