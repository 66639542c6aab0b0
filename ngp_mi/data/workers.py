"""Worker processes for long data jobs: each runs a part of the job and reports its progress and result.

``run_workers(target, count, bar)`` starts ``count`` spawned processes (a fresh interpreter: no
forked JIT or thread state) running ``target(worker, progress)``; ``progress.start(total, before)``
and ``progress.update(n)`` move the parent's progress bar, the value ``target`` returns comes back
to the parent, and an exception (or a worker killed from outside) comes back as the reason it
failed. ``target`` must be picklable (a module-level function or a ``functools.partial`` of one).

A worker exits as soon as its parent is gone (killed with ``kill -9``, or by a ``timeout``): a
watchdog thread sees the parent's pid change within :data:`WATCHDOG_SECONDS` and ends the process,
so no orphan keeps writing into the job's output. Writers are atomic, so what it leaves is whole.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import sys
import threading
import time
from typing import Any, Callable

WATCHDOG_SECONDS = 0.2


class BarProgress:
    """Progress of work done in this process: moves a tqdm bar."""

    def __init__(self, bar: Any):
        self.bar = bar

    def start(self, total: int, before: int) -> None:
        self.bar.total = total
        self.bar.update(before)

    def update(self, done: int) -> None:
        self.bar.update(done)


class _QueueProgress:
    """The same reports from a worker, sent to the parent."""

    def __init__(self, messages: Any, worker: int):
        self.messages, self.worker = messages, worker

    def start(self, total: int, before: int) -> None:
        self.messages.put(("start", self.worker, (total, before)))

    def update(self, done: int) -> None:
        self.messages.put(("update", self.worker, done))


def _exit_with_parent(parent: int) -> None:
    """Poll the parent's pid; when this process has been re-parented, end it at once."""
    while True:
        if os.getppid() != parent:
            print(f"{multiprocessing.current_process().name}: parent {parent} is gone, exiting", file=sys.stderr)
            os._exit(3)  # no clean-up: the atomic writers leave whole files or none
        time.sleep(WATCHDOG_SECONDS)


def _worker_main(target: Callable[[int, Any], Any], worker: int, messages: Any, parent: int) -> None:
    threading.Thread(target=_exit_with_parent, args=(parent,), name="parent-watchdog", daemon=True).start()
    try:
        result = target(worker, _QueueProgress(messages, worker))
        messages.put(("done", worker, result))
    except BaseException as exc:
        messages.put(("failed", worker, f"{type(exc).__name__}: {exc}"))
        raise


def run_workers(target: Callable[[int, Any], Any], count: int, bar: Any, name: str = "worker",
                log: Callable[[str], None] = print) -> tuple[dict[int, Any], dict[int, str], dict[int, tuple[int, int]]]:
    """Run ``target`` in ``count`` processes; returns (results, failure reasons, (total, before) per worker)."""
    context = multiprocessing.get_context("spawn")
    messages = context.Queue()
    processes = [context.Process(target=_worker_main, args=(target, j, messages, os.getpid()), name=f"{name}-{j}", daemon=True)
                 for j in range(count)]
    for process in processes:
        process.start()
    totals: dict[int, tuple[int, int]] = {}
    results: dict[int, Any] = {}
    failures: dict[int, str] = {}
    silent_exit: set[int] = set()
    try:
        while len(results) + len(failures) < count:
            try:
                kind, worker, payload = messages.get(timeout=0.5)
            except queue.Empty:
                for j, process in enumerate(processes):
                    if j in results or j in failures or process.exitcode is None:
                        continue
                    if j in silent_exit:  # exited a whole timeout ago without a final message: killed
                        failures[j] = f"exited with code {process.exitcode}"
                        log(f"worker {j} {failures[j]}")
                    silent_exit.add(j)
                continue
            if kind == "start":
                totals[worker] = payload
                bar.total = sum(t for t, _ in totals.values())
                bar.update(payload[1])
            elif kind == "update":
                bar.update(payload)
            elif kind == "done":
                results[worker] = payload
            else:
                failures[worker] = payload
                log(f"worker {worker} failed: {payload}")
    finally:
        for process in processes:
            process.join(timeout=None if len(results) + len(failures) == count else 0)
            if process.is_alive():
                process.terminate()
    return results, failures, totals
