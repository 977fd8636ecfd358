"""Atomic file writes with the permissions a plain ``open`` would give."""
from __future__ import annotations

import os
import tempfile
from typing import Callable, IO


def default_mode() -> int:
    """0o666 less the process's umask (what ``open(path, "w")`` creates), read without
    changing the umask where Linux reports it."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: str, write: Callable[[IO[bytes]], None], prefix: str = ".tmp-") -> str:
    """Write a file atomically: ``write(f)`` fills a temporary file in the same folder, which
    is synced, given ``default_mode()`` permissions and renamed over ``path`` (then the folder
    is synced where the OS allows). On any error the temporary file is removed and ``path``
    is untouched. Returns the path."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, default_mode())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:
        dir_fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return path
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
    return path
