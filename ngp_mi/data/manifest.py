"""A dataset folder's manifests: one JSON line per finished view, appended after the view's files.

``manifest[.shard-K-of-N].jsonl`` files are written by the processes of ``render-dataset`` (one per
shard or worker) and read together by :func:`load_manifest`.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
from pathlib import Path
from typing import Any, Callable

log = logging.getLogger("ngp_mi.render_dataset")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Records of a JSON-lines file; a torn last line (a killed writer) is ignored."""
    records = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s: ignoring a torn line", path)
    return records


def manifest_records(root: str | Path) -> dict[tuple[str, int], dict[str, Any]]:
    """Every view record of a dataset folder (all manifests), keyed by (shape id, view)."""
    return {(r["shape_id"], r["view"]): r for path in sorted(Path(root).glob("manifest*.jsonl"))
            for r in read_jsonl(path)}


def load_manifest(root: str | Path) -> list[dict[str, Any]]:
    """All view records of a dataset folder (every shard's manifest), sorted by (shape, view)."""
    records = manifest_records(root)
    if not records:
        raise ValueError(f"{root}: no manifest*.jsonl with records; render the dataset first")
    return [records[k] for k in sorted(records)]


class ManifestWriter:
    """Appends records, one line each; drops a torn last line left by a killed run first.

    Each line is flushed to the OS, which survives the process being killed (the failure a long
    job must tolerate); it is not fsync'ed per view (1 ms each), so a power loss may lose the last
    records, whose views are then simply rendered again.
    """

    def __init__(self, path: Path):
        self.path = path
        if path.exists():
            text = path.read_bytes()
            if text and not text.endswith(b"\n"):
                path.write_bytes(text[: text.rfind(b"\n") + 1])
        self.file = open(path, "a")

    def append(self, record: dict[str, Any]) -> None:
        self.file.write(json.dumps(record) + "\n")
        self.file.flush()

    def close(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()


class BackgroundWriter:
    """Writes each view's files and then its manifest line on ``threads`` threads.

    EXR compression releases the GIL for part of its work, so writes overlap each other and the
    next view's rendering. A view's line follows its own files; lines of different views may come
    in any order (readers sort). A failed write (disk full, permissions) stops the job at the
    next submit.
    """

    def __init__(self, manifest: ManifestWriter, threads: int = 2, depth: int = 16):
        self.manifest = manifest
        self.jobs: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self.lock = threading.Lock()
        self.threads = [threading.Thread(target=self._run, name=f"render-dataset-writer-{i}", daemon=True)
                        for i in range(threads)]
        for thread in self.threads:
            thread.start()

    def submit(self, write: Callable[[], None], record: dict[str, Any], done: Callable[[], None]) -> None:
        if self.error is not None:
            raise self.error
        self.jobs.put((write, record, done))

    def _run(self) -> None:
        while (job := self.jobs.get()) is not None:
            write, record, done = job
            if self.error is None:
                try:
                    write()
                    with self.lock:
                        self.manifest.append(record)
                        done()
                except BaseException as exc:  # reported to the main thread
                    self.error = exc

    def close(self) -> None:
        for _ in self.threads:
            self.jobs.put(None)
        for thread in self.threads:
            thread.join()
        self.manifest.close()
        if self.error is not None:
            raise self.error
