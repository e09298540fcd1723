"""Estimate the mutation kill rate from a seeded random sample of mutmut's mutants.

The whole run (``mutmut run``, about 6,500 mutants of the modules in ``[tool.mutmut]``) takes
hours on two cores because the mutants of widely used functions run many tests each. A uniform
random sample gives the kill rate with a known error in a fraction of the time::

    pip install '.[dev,mutation]'
    python tools/mutation_sample.py --size 300 --seed 0

It generates the mutants if needed (``mutmut run`` on no mutant), draws ``--size`` of them with
``--seed``, runs those not yet checked, and prints the kill rate overall (with its 95 % Wilson
interval) and per module, and the survivors to look at with ``mutmut show NAME``. "No tests"
(a function that no selected test calls) counts as a survivor.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KILLED = {1, 3, 36, 24, -24, 152, 255, 37}  #: exit codes mutmut counts as killed or timed out


def _mutmut() -> list[str]:
    exe = Path(sys.executable).with_name("mutmut")
    return [str(exe)] if exe.exists() else ["mutmut"]


def _codes() -> dict[str, int | None]:
    out: dict[str, int | None] = {}
    for meta in sorted((ROOT / "mutants").rglob("*.meta")):
        out.update(json.loads(meta.read_text())["exit_code_by_key"])
    return out


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=300, help="mutants in the sample (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the draw (default 0)")
    args = ap.parse_args(argv)
    if args.size < 1:
        ap.error("--size must be at least 1")
    if not _codes():  # generate the mutants and the test statistics; mutmut then refuses the name
        subprocess.run([*_mutmut(), "run", "no-such-mutant"], cwd=ROOT, check=False,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    codes = _codes()
    if not codes:
        print("mutmut generated no mutants: check [tool.mutmut] in pyproject.toml", file=sys.stderr)
        return 2
    names = sorted(codes)
    sample = sorted(random.Random(args.seed).sample(names, min(args.size, len(names))))
    todo = [n for n in sample if codes[n] is None]
    if todo:  # one call: each call re-collects the test statistics first
        subprocess.run([*_mutmut(), "run", *todo], cwd=ROOT, check=False, stdout=subprocess.DEVNULL)
    codes = _codes()
    unchecked = [n for n in sample if codes[n] is None]
    if unchecked:
        print(f"{len(unchecked)} sampled mutants were not checked (interrupted?): {unchecked[:5]}", file=sys.stderr)
        return 2
    by_module: dict[str, Counter] = defaultdict(Counter)
    survivors = []
    for n in sample:
        module = n.split(".x_")[0].split(".xǁ")[0]
        killed = codes[n] in KILLED
        by_module[module]["killed" if killed else "survived"] += 1
        if not killed:
            survivors.append((n, codes[n]))
    k = sum(c["killed"] for c in by_module.values())
    lo, hi = _wilson(k, len(sample))
    print(f"sample of {len(sample)} of {len(names)} mutants (seed {args.seed}): "
          f"{k} killed, kill rate {k / len(sample):.1%} (95 % interval {lo:.1%}-{hi:.1%})")
    for module in sorted(by_module):
        c = by_module[module]
        n = c["killed"] + c["survived"]
        print(f"  {module:45s} {c['killed']:4d}/{n:<4d} {c['killed'] / n:6.1%}")
    print("survivors (mutmut show NAME):")
    for n, code in survivors:
        print(f"  {n}  [{'no tests' if code in (5, 33) else f'exit {code}'}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
