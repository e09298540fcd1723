"""Helper of test_study: a process pool with the study's worker initializer, one long job."""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor


def job(path: str) -> None:
    with open(path, "w") as fh:
        fh.write(str(os.getpid()))
    time.sleep(60)


if __name__ == "__main__":
    from deploy.study import _stop_with_parent

    pool = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=_stop_with_parent)
    pool.submit(job, sys.argv[1])
    time.sleep(120)
