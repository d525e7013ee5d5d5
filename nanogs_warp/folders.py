"""A folder the tool writes into: made when missing, and refused in one line when it cannot be."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import InputError


def writable_folder(path: Path, what: str) -> Path:
    """``path`` made (with its parents) if missing; InputError, prefixed ``what``, when it cannot be
    made or written into."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{what}: cannot create the directory: {e.strerror or e}") from None
    if not os.access(path, os.W_OK):
        raise InputError(f"{what}: the directory is not writable")
    return path
