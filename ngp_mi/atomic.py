"""Files and folders written atomically: under a temporary name in the same folder, then one rename.

A job killed mid-write leaves the previous version (or nothing), never a partial file, and a
reader never sees one. Every writer of the package goes through :func:`atomic_path`; the
temporary names start with ``.<name>.`` so that globs of finished files never match them.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FOLDER_MODE = 0o777 & ~_umask()  # what mkdir gives; mkdtemp makes folders private (0700)
_FILE_MODE = 0o666 & ~_umask()  # what open gives; some writers (safetensors) make files private (0600)


@contextlib.contextmanager
def atomic_path(path: str | Path, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (with the same suffix, for writers that read it) and
    rename it to ``path`` when the block ends without an error; remove it otherwise.

    With ``directory``, the temporary path is a new empty folder, and an existing ``path`` folder is
    replaced. Parent folders are created.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if directory:
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        os.chmod(tmp, _FOLDER_MODE)
    else:  # unique per process and thread, and not created here (cheaper than mkstemp: the EXR writer is hot)
        tmp = path.with_name(f".{path.name}.{os.getpid()}-{threading.get_ident()}{path.suffix}")
    try:
        yield tmp
        if directory and path.is_dir():
            shutil.rmtree(path)
        if not directory and tmp.exists():
            os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | Path, data: Any, indent: int | None = 1) -> Path:
    """Write ``data`` as JSON (one trailing newline) to ``path`` atomically."""
    return write_text(path, json.dumps(data, indent=indent) + "\n")
