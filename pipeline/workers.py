"""Local Dask workers: each bound to its own share of the machine's cores.

Imported by the Dask executor only (and by the workers, to unpickle the plugin), so the CLI does
not pay for importing distributed on serial runs.
"""
from __future__ import annotations

import logging
import os

from distributed.diagnostics.plugin import WorkerPlugin


def cpu_shares(cpus: list[int], n: int) -> list[tuple[int, ...]]:
    """Split `cpus` among n workers: disjoint, contiguous shares differing by at most one core
    when n <= len(cpus); one core each, taken in turn, when there are more workers than cores."""
    if n > len(cpus):
        return [(cpus[i % len(cpus)],) for i in range(n)]
    q, r = divmod(len(cpus), n)
    starts = [i * q + min(i, r) for i in range(n + 1)]
    return [tuple(cpus[a:b]) for a, b in zip(starts, starts[1:])]


class PinToShare(WorkerPlugin):
    """Dask worker plugin: bind local worker `name` (0..n-1) to its share of the cores.

    Each thread pool in a worker then sizes itself to the share: OpenVDB's TBB and Taichi
    (init_taichi) read the binding, llvmpipe gets LP_NUM_THREADS. Unbound, every worker's TBB
    took the whole machine, and two workers on 2 cores ran the example shot's surface stage
    19% slower (most of it system time spent switching threads). The binding is set on every
    thread of the process and again on each restarted worker (a registered plugin is attached
    to workers that join later); threads made later, from the task thread, inherit it.
    """
    def __init__(self, shares: list[tuple[int, ...]]):
        self.shares = shares

    def setup(self, worker) -> None:
        share = self.shares[int(worker.name) % len(self.shares)]
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), share)
            except OSError:              # a thread that ended since listdir
                pass
        os.environ["LP_NUM_THREADS"] = str(len(share))    # read when a render window opens


class QuietLogs(WorkerPlugin):
    """Dask worker plugin: a local worker's own distributed log lines are not printed.

    A heartbeat that races the scheduler's shutdown at the end of a run (after a failed frame,
    say) printed a `Failed to communicate with scheduler` traceback into the user's terminal.
    Nothing a worker logs is the user's news: a task's failure comes back through its future and
    is reported as one line naming the frame, and a worker that dies is reported by its nanny,
    which runs in the CLI's process.
    """
    def setup(self, worker) -> None:
        set_distributed_log_level(logging.CRITICAL)


def set_distributed_log_level(level: int) -> None:
    """Set `distributed` and every logger below it that exists (some have their own level)."""
    for name in ["distributed", *logging.root.manager.loggerDict]:
        if name == "distributed" or name.startswith("distributed."):
            logging.getLogger(name).setLevel(level)
