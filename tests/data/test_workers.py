"""Worker processes: progress and results come back; a failing or killed worker is reported with its reason."""

import functools
import os
import subprocess
import sys
import time

from helpers import ROOT, Bar, alive, worker_job

from ngp_mi.data.workers import run_workers


def test_results_progress_and_failures_come_back():
    bar, messages = Bar(), []
    results, failures, totals = run_workers(functools.partial(worker_job, fail=2), 3, bar, log=messages.append)
    assert results == {0: 0, 1: 10} and totals == {0: (4, 1), 1: (4, 1), 2: (4, 1)}
    assert failures == {2: "ValueError: worker 2 was told to fail"} and "worker 2 failed" in messages[0]
    assert bar.total == 12 and bar.n == 3 + 2 * 3  # the views present before, then the done ones


def test_workers_exit_when_their_parent_is_killed(tmp_path):
    parent = subprocess.Popen([sys.executable, "-c", (
        "import functools, helpers\n"
        "from ngp_mi.data.workers import run_workers\n"
        f"run_workers(functools.partial(helpers.sleeping_job, {str(tmp_path)!r}), 2, helpers.Bar())\n")],
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])})
    deadline = time.monotonic() + 120
    while len(list(tmp_path.glob("*.pid"))) < 2:
        assert time.monotonic() < deadline and parent.poll() is None, "the workers did not start"
        time.sleep(0.1)
    pids = [int(p.read_text()) for p in tmp_path.glob("*.pid")]
    parent.kill()  # SIGKILL to the parent alone: its workers are re-parented, not signalled
    parent.wait()
    time.sleep(2)
    assert not [pid for pid in pids if alive(pid)]
