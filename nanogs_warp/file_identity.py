"""Whether two paths name the same file: by the file's identity, not its path (a module of its
own, light enough for ``batch``'s scan of its scenes, which imports nothing heavier)."""

from __future__ import annotations

import os


def file_identity(path, follow_links: bool = True) -> tuple[int, int] | None:
    """(device, inode) of what ``path`` names, links followed (``follow_links=False``: of a link
    itself); None where nothing is there or it cannot be told. Two paths name the same file or
    folder exactly when these agree, whatever bind mounts or links lie between them (a volume
    mounted twice in a container, ``mount --bind``), where comparing resolved paths would not see it."""
    try:
        st = os.stat(path, follow_symlinks=follow_links)
    except (OSError, ValueError):  # missing, unreadable, a link loop, a NUL in the name
        return None
    return st.st_dev, st.st_ino
