"""Helper of test_study: a process pool of the studies' (:func:`deploy.worker_pool.worker_pool`).

``_pool_probe.py PID_FILE``: one long job (the study process is then killed).
``_pool_probe.py PID_FILE SECOND_FILE``: two long jobs queued to one worker, each run as the
study runs a seed; the test sends the worker SIGTERM during the first one.
"""

from __future__ import annotations

import os
import sys
import time


def job(path: str) -> None:
    with open(path, "w") as fh:
        fh.write(str(os.getpid()))
    time.sleep(60)


if __name__ == "__main__":
    from slcp.deploy.study import _interruptible
    from slcp.deploy.worker_pool import worker_pool

    pool = worker_pool(1)
    if len(sys.argv) == 2:
        pool.submit(job, sys.argv[1])
    else:
        for path in sys.argv[1:3]:
            pool.submit(_interruptible, job, path)
    time.sleep(120)
