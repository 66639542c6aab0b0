"""Lock files that name their holder: one job at a time writes a folder (or a shard of it).

:func:`exclusive` holds an advisory ``flock`` on a file for as long as a block runs and writes who
holds it (pid, host, start time, command) into the file; a second job asking for it gets
:class:`Busy`, which says who. The operating system drops the lock when its process dies, however
it dies (``kill -9`` included), so no stale lock ever needs removing by hand; the file itself
stays behind with the last holder's name.

Helper processes of a job (dataset workers) hold the same kind of lock *shared* on a second file
(:func:`shared`), and the next job waits for them (:func:`wait_exclusive`): a job killed on its own
leaves its workers running for the moment they need to notice (:mod:`ngp_mi.data.workers`), and the
next job must not write beside them.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import IO, Iterator


class Busy(RuntimeError):
    """Another process holds the lock; the message names it."""


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
        return (f"pid {info['pid']} on {info['host']} since {info['started']} "
                f"({' '.join(info.get('command', [])) or 'no command'})")
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


def _open(path: Path) -> IO[str]:
    path.parent.mkdir(parents=True, exist_ok=True)
    return open(path, "a+")  # not "w": truncating before holding the lock would erase the holder's name


@contextlib.contextmanager
def exclusive(path: str | Path, what: str, wait: float = 0.0) -> Iterator[None]:
    """Hold ``path`` for this process while the block runs, or raise :class:`Busy` naming its holder.

    ``wait`` > 0 gives the holder that many seconds to finish first (jobs started together that
    share a cache: the first renders it, the others then find it complete); said once on stderr."""
    path = Path(path)
    with _open(path) as f:
        deadline, said = time.monotonic() + wait, False
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise Busy(f"{path}: {what} is being written by {_holder(path)}; wait for it to finish or "
                               "stop it") from None
                if not said:
                    print(f"{path}: {what} is being written by {_holder(path)}; waiting up to {wait:.0f} s",
                          file=sys.stderr, flush=True)
                    said = True
                time.sleep(min(0.5, max(deadline - time.monotonic(), 0.0)))
        f.seek(0)
        f.truncate()
        f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                            "started": datetime.datetime.now().isoformat(timespec="seconds"),
                            "command": sys.argv}) + "\n")
        f.flush()
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@contextlib.contextmanager
def shared(path: str | Path) -> Iterator[None]:
    """Hold ``path`` shared (with the other helpers of one job) while the block runs."""
    with _open(Path(path)) as f:
        fcntl.flock(f, fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def wait_exclusive(path: str | Path, what: str, timeout: float = 30.0) -> None:
    """Wait until no process holds ``path`` shared (the helpers of an earlier job have exited); after
    ``timeout`` seconds raise :class:`Busy`."""
    path = Path(path)
    deadline = time.monotonic() + timeout
    with _open(path) as f:
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(f, fcntl.LOCK_UN)
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise Busy(f"{path}: processes of an earlier {what} job still write here after {timeout:.0f} s; "
                               "stop them (they hold this file open) and re-run") from None
                time.sleep(0.1)
