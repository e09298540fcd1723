"""Range-gate outcomes over many seeds, in process: how many of the ranges the emulator injected
as clean, NLOS or gross outliers each gate refused, per CI method (``slcp scenario gates``).

Each seed is a full in-process run (:func:`deploy.inprocess.run_inprocess`, every method, the
run's seed also redrawing the stops as in ``slcp run --seed``); the runs are spread over the cores.
"""

from __future__ import annotations

import os

from .worker_pool import worker_pool

#: outcomes of :meth:`agent.methods.MethodFilter.range` that count as rejected by a gate
REJECTED_PREFIX = "gate"


def _one_seed(args: tuple[str, int]) -> dict[str, dict[str, dict[str, int]]]:
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth

    from .inprocess import run_inprocess

    scenario, seed = args
    return run_inprocess(build_truth(load_scenario(scenario), stop_seed=seed), seed).range_outcomes


def range_outcomes(scenario: str, seeds: list[int], processes: int | None = None) -> dict:
    """Range outcomes summed over ``seeds``: method -> injected kind -> outcome -> count."""
    total: dict[str, dict[str, dict[str, int]]] = {}
    workers = max(1, min(processes or os.cpu_count() or 1, len(seeds)))
    with worker_pool(workers) as pool:
        for ro in pool.map(_one_seed, [(scenario, s) for s in seeds]):
            for m, kinds in ro.items():
                for kind, outcomes in kinds.items():
                    d = total.setdefault(m, {}).setdefault(kind, {})
                    for o, c in outcomes.items():
                        d[o] = d.get(o, 0) + c
    return total


def summarise(total: dict) -> dict:
    """Per method and injected kind: ``n``, ``rejected`` (by any gate), ``rejected_share``,
    ``fused`` and the ``outcomes`` themselves."""
    out: dict = {}
    for m, kinds in sorted(total.items()):
        for kind, outcomes in sorted(kinds.items()):
            n = sum(outcomes.values())
            rej = sum(c for o, c in outcomes.items() if o.startswith(REJECTED_PREFIX))
            out.setdefault(m, {})[kind] = {
                "n": n,
                "rejected": rej,
                "rejected_share": rej / n if n else None,
                "fused": outcomes.get("fused", 0),
                "outcomes": dict(sorted(outcomes.items())),
            }
    return out
