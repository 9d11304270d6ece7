"""Saving files so that nothing is lost: a crash or a full disk leaves the old file whole."""

from __future__ import annotations

import contextlib
import os
import tempfile


TEMPORARY_PREFIX = ".tmp-"


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike):
    """Yields a binary file in ``path``'s directory; when the block ends without an error it is
    flushed to disk and renamed over ``path`` (then the directory is synced). On an error the
    temporary file is removed and ``path`` is left as it was; an ``OSError`` (a full disk, a
    missing directory) is raised again naming ``path``."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=TEMPORARY_PREFIX, suffix="-" + os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # as open() would have made it (mkstemp makes 0600)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None:
            raise OSError(e.errno, f"cannot write {path}: {e.strerror or e}") from e
        raise
    with contextlib.suppress(OSError):
        dir_fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def remove_leftovers(path: str | os.PathLike):
    """Removes the temporary files that ``atomic_write(path)`` left where a kill interrupted it
    (``.tmp-*-NAME`` beside ``path``). For a file one process writes, at the start of its run."""
    path = os.fspath(path)
    directory, name = os.path.split(os.path.abspath(path))
    with contextlib.suppress(OSError):
        for entry in os.listdir(directory):
            middle = entry[len(TEMPORARY_PREFIX):-len(name) - 1]  # mkstemp's random letters
            if entry == f"{TEMPORARY_PREFIX}{middle}-{name}" and middle.replace("_", "").isalnum():
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(directory, entry))
