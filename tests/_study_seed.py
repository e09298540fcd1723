"""Helper of test_study: a study runner (``run_study(runner=...)``) in which one seed cannot
start. Imported by the study's spawned pool workers, so it lives in a module of its own.

Seed ``BAD_SEED``'s emulator is replaced by a process that never publishes (as the emulator of
a stalled start did), so no agent ever reports; the launcher's watchdog kills it, resumes it
once, sees it fail at the same point and gives up. Every other seed is a real, short fleet run.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

BAD_SEED = 1
TRIES_FILE = "tries.txt"  #: each try of the bad seed appends a line here (in the study folder)


def runner(scenario: str, methods: tuple[str, ...], seed: int, out: str, fusion: str, sign: bool,
           agent_nice: int = 5, lane_constraint: bool = True, zenoh_mode: str = "client", secure: bool = True,
           lanelet2: bool = False) -> dict:
    from slcp.deploy import launcher, supervisor

    if seed == BAD_SEED:
        with open(Path(out).parent / TRIES_FILE, "a") as fh:
            fh.write(f"{seed}\n")
        real = supervisor._slcp
        supervisor._slcp = lambda *a: ([sys.executable, "-c", "import time; time.sleep(600)", *real(*a)]
                                     if "emulate" in a else real(*a))
        launcher._supervise = functools.partial(launcher._supervise, stall_s=1.0)
    # the bad seed's watchdog fires after wait_agents + stall_s without a report: kept short
    return launcher.run_fleet(scenario, methods, None, seed, Path(out), None, fusion, sign, agent_nice=agent_nice,
                              lane_constraint=lane_constraint, zenoh_mode=zenoh_mode, secure=secure,
                              lanelet2=lanelet2, wait_agents=1.0 if seed == BAD_SEED else 3.0)
