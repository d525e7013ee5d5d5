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


def creatable_folder(path: Path, what: str) -> Path:
    """Checks, without making anything, that ``path`` is a writable folder or could be made as one
    (its nearest existing ancestor a writable folder); InputError, prefixed ``what``, when not. A
    command that fails before it writes then leaves no empty folder behind."""
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    if existing is None or not existing.is_dir():
        raise InputError(f"{what}: cannot create the directory: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{what}: the directory {existing} is not writable")
    return path
