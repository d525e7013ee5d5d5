"""Opening an input file for reading: only a regular file, so that a FIFO, a device or a socket named
like a scene (``mkfifo scene.ply``, ``/dev/zero``) is refused at once instead of blocking the open or
the read for ever."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import InputError


def open_regular(path: Path):
    """``path`` opened for binary reading, or InputError (missing, unreadable, a directory or not a
    regular file). The open does not block: a FIFO is opened non-blocking and refused by its type."""
    name = path.name
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        raise InputError(f"{name}: no such file") from None
    except PermissionError:
        raise InputError(f"{name}: permission denied") from None
    except IsADirectoryError:
        raise InputError(f"{name}: is a directory") from None
    except OSError as e:
        raise InputError(f"{name}: cannot read the file: {e.strerror or e}") from e
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise InputError(f"{name}: is a directory")
        if not stat.S_ISREG(mode):
            raise InputError(f"{path}: not a regular file (a pipe, device or socket); give a file")  # "null" alone says little
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
