"""The one exception type that user-facing code turns into a one-line message and exit code 2."""

import os
import re
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager


def debugging() -> bool:
    """Whether NANOGS_DEBUG asks for tracebacks and Warp's own messages: set, and not "" or "0"."""
    return os.environ.get("NANOGS_DEBUG", "") not in ("", "0")


class InputError(Exception):
    """Bad input or an impossible request: the message is shown to the user as one line."""


class NanogsWarning(UserWarning):
    """Something the user should know that does not stop the work (e.g. PLY elements dropped): the
    commands show it as one line on stderr."""


@contextmanager
def package_warnings(note: Callable[[str], None]) -> Iterator[None]:
    """Runs the block with the package's own warnings (``NanogsWarning``) recorded, then hands each
    to ``note`` as a line for the user (on stderr, in a summary); any other warning is shown as
    Python would. When the block raises, its warnings go with it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", NanogsWarning)
        yield
    for warning in caught:
        if issubclass(warning.category, NanogsWarning):
            note(str(warning.message))
        else:
            warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)


def printable(message: str) -> str:
    """``message`` with its control characters (a newline in a file's name) written as escapes, so
    that a line of output stays one line."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in message)


LONGEST_LINE = 1000  # characters of a one-line message shown; longer ones lose their middle


def elided(text: str, most: int) -> str:
    """``text``, or where it is longer than ``most`` characters (a value or path of thousands of
    characters from a hostile file) its start and end, two to one, with how many characters it
    leaves out between them."""
    if len(text) <= most:
        return text
    head, tail = most * 2 // 3, most // 3
    return f"{text[:head]}[... {len(text) - head - tail:,} characters ...]{text[-tail:]}"


def one_line(message: str) -> str:
    """``printable(message)``, ``elided`` to LONGEST_LINE characters: the name and the reason are at
    its start and end."""
    return elided(printable(message), LONGEST_LINE)


def out_of_memory(error: BaseException) -> str | None:
    """The line to show when ``error`` says that memory ran out: Python's ``MemoryError``, or Warp's
    failed allocation on a device (a scene too large for the GPU, or a host at its limit); None
    for any other error."""
    if isinstance(error, MemoryError):
        return "out of memory"
    match = _WARP_ALLOCATION.match(str(error)) if isinstance(error, RuntimeError) else None
    if match is None:
        return None
    return f"out of memory on {match['device']}: could not allocate {int(match['bytes']):,} bytes"


_WARP_ALLOCATION = re.compile(r"Failed to allocate (?P<bytes>\d+) bytes (?:with \w+ )?on device '(?P<device>[^']+)'")
