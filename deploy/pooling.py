"""An idealised reference between the distributed filters and the joint bound: the fleet's
own-sensor estimates pooled at each instant.

At every record time, each vehicle's own-sensor estimate (SL-SP by default: no cooperation, so
two vehicles' errors share nothing but the common-mode GNSS error) is fused with its reported
covariance, under a relative geometry taken as known exactly (one translation of the whole fleet
fitted to all of them). No estimator can do that: UWB does not give every pair's vector, the
common-mode error is shared, and nothing is carried over time. So it shows what one-shot pooling
of what each vehicle knows by itself is worth, beside the joint bound that also pools over time
(docs/algorithms.md, *The physical limit*).

``python -m slcp.deploy.pooling rush-hour --seeds 0,1`` runs the fleet in process and prints, per
vehicle, the RMSE, ANEES and RMSE over the SL-CP bound while it truly stands: the pooled
reference beside SL-SP and SL-CP. Pure numpy apart from the run itself.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

import numpy as np


def pool_translation(err_ne: dict[str, np.ndarray], cov_ne: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Fuse the vehicles' estimates of one common translation.

    Parameters
    ----------
    err_ne : dict
        vehicle -> horizontal errors (north, east) [m], shape (n, 2), at common times.
    cov_ne : dict
        vehicle -> their reported covariances [m²], shape (n, 2, 2).

    Returns
    -------
    err : ndarray
        The pooled error (n, 2) [m]: with the relative geometry exact, every vehicle's.
    cov : ndarray
        Its covariance (n, 2, 2) [m²], ``(Σ P_v⁻¹)⁻¹``: the errors taken as independent.
    """
    ids = sorted(err_ne)
    if not ids:
        raise ValueError("no vehicles to pool")
    info = sum(np.linalg.inv(cov_ne[v]) for v in ids)
    vec = sum(np.einsum("nij,nj->ni", np.linalg.inv(cov_ne[v]), err_ne[v]) for v in ids)
    cov = np.linalg.inv(info)
    return np.einsum("nij,nj->ni", cov, vec), cov


def standing_scores(result, truth, source: str = "SL-SP", compare: tuple[str, ...] = ("SL-SP", "SL-CP")) -> dict:
    """Per vehicle, while it truly stands: sums for RMSE, NEES and the SL-CP bound of the pooled
    ``source`` estimates and of the methods in ``compare`` (:func:`deploy.inprocess.run_inprocess`
    result ``result`` on ``truth``). Sums, so that seeds add up: ``{vehicle: {name: {"se",
    "nees", "b2", "n"}}}``."""
    from .bound import posterior_crlb

    ids = sorted(truth.vehicles)
    pooled, pcov = pool_translation({v: result.err_ne[(v, source)] for v in ids},
                                    {v: result.cov_ne[(v, source)] for v in ids})
    bound = posterior_crlb(truth, ("SL-CP",))
    out: dict = {}
    for v in ids:
        sel = truth.vehicles[v].stopped_at(result.t)
        if not sel.any():
            continue
        b2 = float(np.sum(bound.at("SL-CP", v, result.t[sel]) ** 2))
        rows = {f"pooled {source}": (pooled[sel], pcov[sel])}
        rows.update({m: (result.err_ne[(v, m)][sel], result.cov_ne[(v, m)][sel]) for m in compare})
        out[v] = {}
        for name, (e, c) in rows.items():
            q = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
            out[v][name] = {"se": float(np.sum(e**2)), "nees": float(np.sum(q)), "b2": b2, "n": int(sel.sum())}
    return out


def seeded_sums(prog: str, description: str, argv: list[str] | None,
                per_seed: Callable[[Any, int, argparse.Namespace], dict[str, Any]],
                extra: Callable[[argparse.ArgumentParser], None] | None = None,
                ) -> tuple[argparse.Namespace, Any, dict[str, Any]] | None:
    """The command line of a lab reference run over seeds (``SCENARIO --seeds a,b,…`` and the
    options ``extra(parser)`` adds): the parsed arguments, the scenario and the sums of
    ``per_seed(truth, seed, args)`` (nested dicts ending in dicts of numbers) added over the
    seeds; None (after a one-line error on stderr) for a bad scenario or seed list."""
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth

    ap = argparse.ArgumentParser(prog=f"python -m slcp.deploy.{prog}", description=description)
    ap.add_argument("scenario", help="shipped scenario name or .toml")
    ap.add_argument("--seeds", default="0", help="comma-separated run seeds (default 0)")
    if extra is not None:
        extra(ap)
    args = ap.parse_args(argv)
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
        scn = load_scenario(args.scenario)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return None
    total: dict[str, Any] = {}

    def add(into: dict[str, Any], sums: dict[str, Any]) -> None:
        for key, x in sums.items():
            if isinstance(x, dict):
                add(into.setdefault(key, {}), x)
            else:
                into[key] = into.get(key, 0.0) + x

    for seed in seeds:
        add(total, per_seed(build_truth(scn, stop_seed=seed), seed, args))
    return args, scn, total


def main(argv: list[str] | None = None) -> int:
    from .inprocess import run_inprocess

    def per_seed(truth: Any, seed: int, _args: argparse.Namespace) -> dict[str, Any]:
        return standing_scores(run_inprocess(truth, seed, methods=("SL-SP", "SL-CP")), truth)

    got = seeded_sums("pooling", __doc__.split("\n\n")[0], argv, per_seed)
    if got is None:
        return 2
    args, scn, total = got
    print(f"{scn.name}, seeds {args.seeds}: while each vehicle truly stands; RMSE [m] / RMSE over the "
          "SL-CP bound / ANEES")
    names = next(iter(total.values())).keys() if total else ()
    print(f"{'vehicle':8s} {'bound':>7s} " + " ".join(f"{n:>22s}" for n in names))
    for v, rows in sorted(total.items()):
        b = np.sqrt(next(iter(rows.values()))["b2"] / next(iter(rows.values()))["n"])
        cells = []
        for r in rows.values():
            rmse = np.sqrt(r["se"] / r["n"])
            cells.append(f"{rmse:6.3f} / {rmse / b:5.2f} / {r['nees'] / r['n']:5.2f}")
        print(f"{v:8s} {b:7.3f} " + " ".join(f"{c:>22s}" for c in cells))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
