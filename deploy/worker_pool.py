"""The studies' process pools: spawned workers that stop when the study process is gone.

Spawned, not forked: a fork of a process that runs threads (Zenoh's runtime in a test worker or a
host) copies their locks without the threads, and a child can wait on them. A worker watches its
parent: when the study process is killed (SIGKILL leaves it no time to stop its pool), the worker
sends itself SIGTERM instead of running on with the seeds queued to it, for minutes, on the
machine's cores.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor


def stop_with_parent(parent: int, period: float = 0.5) -> None:
    """Pool-worker initializer: when the study process ``parent`` is gone, terminate this worker
    (SIGTERM: a running fleet's own cleanup, see :func:`deploy.study._interruptible`; an
    in-process seed just ends). The parent's pid comes from the parent: a worker still starting
    when the study is killed would otherwise take its new parent (init) for the study's."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="stop-with-parent", daemon=True).start()


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes that stop with the study process."""
    return ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=stop_with_parent,
                               initargs=(os.getpid(),))
