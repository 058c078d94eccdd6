"""One writer an output directory: an flock on ``DIR/.lock``, held while a command writes there (``wm train``,
``wam train``, ``eval``, ``collect``; a ``--workers`` or ``--ray`` run holds it in the parent, which writes what its
workers return). The kernel drops an flock with the process that held it, so a crashed or killed run leaves no
stale lock behind; the empty ``.lock`` file it leaves is not a lock and binds nothing."""

from __future__ import annotations

import fcntl
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from wamplan.errors import UserError

LOCK_FILE = ".lock"


@contextmanager
def dir_lock(path: str | Path, doing: str = "written", flag: str = "--out") -> Iterator[None]:
    """Hold the existing directory ``path``'s write lock while the block runs; one line if another process holds
    it: "PATH is being DOING by another process now; ...". On a filesystem without flock (some NFS, Lustre, FUSE
    mounts) the block runs unguarded after a note."""
    path = Path(path)
    f = open(path / LOCK_FILE, "a")
    try:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"{path} is being {doing} by another process now; wait for it to end (then re-run to "
                            f"resume) or pass another {flag}") from None
        except OSError as e:
            print(f"note: {path}'s filesystem takes no lock ({e.strerror or e}); do not write into it twice at once")
        yield
    finally:
        f.close()  # releases the lock
