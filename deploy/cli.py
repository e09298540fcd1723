"""``slcp`` command line: the thin shell over the packages (the only place that prints)."""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import logging
import signal
import sys

from . import blas_threads  # noqa: F401  (first: it sets the BLAS threads before numpy loads)
from . import cli_types as T
from .commands import fleet, lab, replay, run, scenario
from .datasets import DatasetError

HANDLERS = {**replay.HANDLERS, **fleet.HANDLERS, **run.HANDLERS, **lab.HANDLERS, **scenario.HANDLERS}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("slcp")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = T.Parser(prog="slcp", description="Stop-line-aided cooperative positioning")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}",
                   help="print the installed version and exit")
    sub = p.add_subparsers(dest="command", required=True)

    replay.add_replay(sub)
    fleet.add_agent(sub)
    fleet.add_emulate(sub)
    fleet.add_router(sub)
    fleet.add_sensors(sub)
    fleet.add_record(sub)
    fleet.add_view(sub)
    run.add_run(sub)
    lab.add_attack_eval(sub)
    fleet.add_keys(sub)
    lab.add_bound(sub)
    lab.add_bench(sub)
    lab.add_soak(sub)
    run.add_report(sub)
    scenario.add_scenario(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if hasattr(signal, "SIGUSR1"):  # `kill -USR1 PID`: every thread's Python stack to stderr (a hung process)
        with contextlib.suppress(OSError, ValueError):  # a stderr without a file descriptor (captured)
            faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
    logging.basicConfig(level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return HANDLERS[args.command](args)
    except (DatasetError, ValueError, OSError) as exc:
        print(f"slcp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nslcp {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
