"""The temporary files outputs are written under, and what a killed writer left of them: names
that carry the writer's process id and process space, and their removal (a module of its own,
light enough for ``batch``'s parent process, which imports no NumPy)."""

from __future__ import annotations

import functools
import hashlib
import os
import secrets
import socket
from pathlib import Path

from .file_identity import file_identity


def through_links(path: Path) -> Path:
    """The file that a symbolic link at ``path`` names, after every link (a shell's redirection
    writes there too); ``path`` itself where it is no link. Renaming a new file over ``path`` would
    replace the link, not the file: ``-o /dev/stdout`` would have replaced the machine's
    ``/dev/stdout`` with a regular file."""
    return Path(os.path.realpath(path)) if os.path.islink(path) else path


def temporary_path(path: Path) -> Path:
    """Where ``path`` is written first: ``.<name>.<pid>-<12 hex>.tmp`` beside it, the first eight hex
    digits ``process_space()``'s. The writer's process id and process space in the name let a later
    run tell what a killed writer left (``remove_stale_temporaries``) from a live writer's file."""
    return path.parent / f".{path.name}.{os.getpid()}-{process_space()}{secrets.token_hex(2)}.tmp"


@functools.lru_cache(maxsize=1)
def process_space() -> str:
    """Eight hex digits naming the space in which this process's id means something: four for the
    machine and its PID namespace (a container's own), four for this boot of the machine, where
    Linux tells them; else the host's name. A process id seen in a shared folder (NFS, a volume
    mounted in several containers) says nothing of whether a writer in another space is alive."""
    host, boot = [socket.gethostname()], ""
    try:
        host.append(str(os.stat("/proc/self/ns/pid").st_ino))
        with open("/proc/sys/kernel/random/boot_id", "rb") as f:
            boot = f.read().decode("ascii", "replace").strip()
    except OSError:
        pass
    return _hex4("\n".join(host)) + _hex4(boot)


def _hex4(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:4]


@functools.lru_cache(maxsize=1)
def _boot_time() -> float | None:
    """When this machine booted (seconds since the epoch), where Linux tells it."""
    try:
        with open("/proc/stat", "rb") as f:
            for line in f:
                if line.startswith(b"btime "):
                    return float(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def remove_stale_temporaries(paths: list[Path]) -> list[Path]:
    """Removes the temporary files of ``paths`` that writers killed on this machine left behind (a
    kill -9, a lost power: no handler ran): those whose process is gone, and those that an earlier
    boot of this machine (in this container) last wrote before this boot began; a live writer's
    stays, and so does every file a writer of another machine or container made
    (``process_space``). One scan per folder. Returns what was removed."""
    removed = []
    paths = [through_links(p) for p in paths]  # written beside the files their links name
    for folder in dict.fromkeys(p.parent for p in paths):
        names = {p.name for p in paths if p.parent == folder}
        try:
            with os.scandir(folder) as entries:
                stale = [e.path for e in entries if _killed_writers_temporary(e, names)]
        except OSError:
            continue
        for path in stale:
            try:
                os.unlink(path)
                removed.append(Path(path))
            except OSError:
                pass
    return removed


def _killed_writers_temporary(entry: os.DirEntry, names: set[str]) -> bool:
    """Whether ``entry`` is ``temporary_path``'s name for one of ``names`` written by a process that
    is gone."""
    if not (entry.name.startswith(".") and entry.name.endswith(".tmp")):
        return False
    name, _, tag = entry.name[1:-4].rpartition(".")
    pid, _, token = tag.partition("-")
    if name not in names or not pid.isdigit() or len(token) != 12 or not all(c in "0123456789abcdef" for c in token):
        return False
    space = process_space()
    if token[:4] != space[:4]:  # another machine's or container's writer: its process id is not ours to ask
        return False
    if token[4:8] != space[4:8]:  # this machine's (and container's) writer of an earlier boot, or a namesake elsewhere
        boot = _boot_time()
        try:
            return boot is not None and entry.stat(follow_symlinks=False).st_mtime < boot  # last written before this boot
        except OSError:
            return False
    try:
        os.kill(int(pid), 0)  # signal 0: only asks whether the process is there
    except (ProcessLookupError, OverflowError):  # gone, or beyond any process id
        return True
    except OSError:  # there, but another user's
        return False
    return False


def remove_if_still(path: Path, identity: tuple[int, int]) -> None:
    """Removes ``path`` if it is still the file of ``identity`` (device, inode): a writer that failed
    part way takes back only its own files, never one another writer has put there since (two nodes
    writing one shared folder)."""
    if file_identity(path, follow_links=False) == identity:
        try:
            os.unlink(path)
        except OSError:
            pass
