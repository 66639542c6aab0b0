"""Worker processes: progress and results come back; a failing or killed worker is reported with its reason."""

import functools

from helpers import worker_job

from ngp_mi.data.workers import run_workers


class Bar:
    total, n = 0, 0

    def update(self, k):
        self.n += k


def test_results_progress_and_failures_come_back():
    bar, messages = Bar(), []
    results, failures, totals = run_workers(functools.partial(worker_job, fail=2), 3, bar, log=messages.append)
    assert results == {0: 0, 1: 10} and totals == {0: (4, 1), 1: (4, 1), 2: (4, 1)}
    assert failures == {2: "ValueError: worker 2 was told to fail"} and "worker 2 failed" in messages[0]
    assert bar.total == 12 and bar.n == 3 + 2 * 3  # the views present before, then the done ones
