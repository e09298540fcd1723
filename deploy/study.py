"""``slcp run SCENARIO --seeds N``: N seeded fleet runs and their statistics.

Each seed is a full fleet run (:func:`deploy.launcher.run_fleet`) in ``<out>/seed-<S>/``; up to
``jobs`` run at once, each in its own worker process. The aggregate goes to ``<out>/study.json``
and ``<out>/report.md``:

- RMSE per window, vehicle and method: mean and standard deviation over the seeds, with the
  along-track and cross-track means;
- ANEES: the horizontal NEES (n = 2) averaged over every estimate of every seed, over the whole
  run and per window, beside the two-sided 95 % band of a consistent filter for N runs,
  ``χ²_{2N}(0.025, 0.975) / N``;
- paired RMSE differences per window and vehicle (CP − SP, SL-CP − SP, SL-CP − CP, SL-SP − SP):
  the mean over the seeds that ran both methods, with its two-sided 95 % Student-t interval, and
  whether the first method is significantly better, worse, or neither (``n.s.``);
- first-stopped detection pooled over the seeds: precision, recall and latency;
- the drivers' draws (:func:`stance_check`): how spread the seeds' stop gaps and lateral offsets
  themselves are, against the scenario's σ.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
from concurrent.futures import as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np

from slcp.agent.methods import DEFAULT_FUSION, METHODS

from .study_report import PAIRS, study_markdown  # noqa: F401  (study_markdown: the study's report)
from .worker_pool import worker_pool

log = logging.getLogger(__name__)


def anees_band(n_runs: int, dim: int = 2, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided χ² band of the ANEES of a consistent filter over ``n_runs`` runs."""
    from scipy.stats import chi2

    a = (1.0 - probability) / 2.0
    return float(chi2.ppf(a, dim * n_runs) / n_runs), float(chi2.ppf(1.0 - a, dim * n_runs) / n_runs)


def stance_check(scn, seeds: list[int]) -> dict:
    """How spread the drivers' draws of these seeds are: per vehicle, the mean over the seeds of
    z² for its stop gap d_s and its lateral offset d_l (z the draw's deviation from the
    scenario's mean in units of its σ), and of their sum, each beside the two-sided 95 % χ² band
    of N draws (``χ²_N / N`` and ``χ²_2N / N``).

    Both are random constants of a run that no sensor of the vehicle sees (only cooperation
    can), so a vehicle's error while it stands first at its line, or keeps to a lane, is largely
    its draws. The sum's mean is the ANEES an estimator would score whose error were exactly its
    two draws, with σ the scenario's: where a column is outside its band, the seeds drew stances
    more (or less) spread than the model, and a consistent filter's ANEES where that error
    dominates is expected outside its band too.
    """
    from slcp.hw_emulation.truth import stance_draws

    n = len(seeds)
    draws = [stance_draws(scn, s) for s in seeds]
    out = {}
    for v in scn.vehicles:
        z = np.array([[(d[v.id][0] - v.stop_gap[0]) / v.stop_gap[1] if v.stop_gap[1] > 0 else 0.0,
                       (d[v.id][1] - v.lateral[0]) / v.lateral[1] if v.lateral[1] > 0 else 0.0] for d in draws])
        cell = {}
        for name, q, dim in (("stop_gap", z[:, 0] ** 2, 1), ("lateral", z[:, 1] ** 2, 1), ("both", (z**2).sum(1), 2)):
            lo, hi = anees_band(n, dim)
            a = float(np.mean(q))
            cell[name] = {"mean_z2": a, "band": [lo, hi], "inside": bool(lo <= a <= hi)}
        out[v.id] = cell
    return out


#: (method, reference) pairs whose per-seed RMSE differences the study reports


def paired_difference(a: np.ndarray, b: np.ndarray, probability: float = 0.95) -> dict:
    """Paired difference of two methods' RMSE over the same seeds.

    Parameters
    ----------
    a, b : ndarray, shape (n,)
        Per-seed RMSE [m] of the method and of its reference, seed for seed.
    probability : float
        Coverage of the two-sided Student-t interval of the mean difference.

    Returns
    -------
    dict
        ``mean_m`` (mean of a − b over the seeds where both are finite; None if there is none),
        ``half_width_m`` (None for fewer than 2 seeds), ``n_seeds``,
        and ``verdict``: ``better`` if the whole interval is below 0, ``worse`` if above, else
        ``n.s.`` (with one seed, the sign of the difference alone decides nothing: ``n.s.``).
    """
    from scipy.stats import t as student_t

    d = np.asarray(a, float) - np.asarray(b, float)
    d = d[np.isfinite(d)]  # a seed without a figure for either method is not a pair
    n = len(d)
    if n == 0:
        return {"mean_m": None, "half_width_m": None, "n_seeds": 0, "verdict": "n.s."}
    mean = float(d.mean())
    if n < 2:
        return {"mean_m": mean, "half_width_m": None, "n_seeds": n, "verdict": "n.s."}
    half = float(student_t.ppf(0.5 + probability / 2.0, n - 1) * d.std(ddof=1) / np.sqrt(n))
    verdict = "better" if mean + half < 0.0 else "worse" if mean - half > 0.0 else "n.s."
    return {"mean_m": mean, "half_width_m": half, "n_seeds": n, "verdict": verdict}


def _one(scenario: str, methods: tuple[str, ...], seed: int, out: str, fusion: str, sign: bool,
         agent_nice: int = 5, lane_constraint: bool = True, zenoh_mode: str = "client", secure: bool = True,
         lanelet2: bool = False) -> dict:
    from .launcher import run_fleet

    return run_fleet(scenario, methods, None, seed, Path(out), None, fusion, sign, agent_nice=agent_nice,
                     lane_constraint=lane_constraint, zenoh_mode=zenoh_mode, secure=secure, lanelet2=lanelet2)


def _interruptible(fn, *args):
    """Run ``fn(*args)`` in a pool worker. SIGTERM and SIGHUP raise KeyboardInterrupt, so that
    ``fn``'s own cleanup runs (a fleet stops its processes), and a worker so interrupted then
    exits: a pool worker would otherwise take the next call already queued to it (a seed
    behind the interrupted one) and start another fleet."""
    import logging

    from .supervisor import interrupt_on_termination

    logging.basicConfig(level=logging.WARNING)
    interrupt_on_termination()
    try:
        return fn(*args)
    except KeyboardInterrupt:
        logging.shutdown()
        os._exit(130)  # a process boundary: the pool sees a worker gone, not a result


class StudyError(RuntimeError):
    """No seed of a study finished: there is nothing to aggregate."""


def run_study(scenario: str, seeds: list[int], methods: tuple[str, ...] = METHODS, out: Path = Path("runs/study"),
              fusion: str = DEFAULT_FUSION, jobs: int | None = None, progress=None, sign: bool = True,
              agent_nice: int = 5, lane_constraint: bool = True, zenoh_mode: str = "client",
              runner=None, retries: int = 1, secure: bool = True, lanelet2: bool = False) -> dict:
    """Run the seeds and aggregate; ``progress(done, total, seed)`` after each finished seed.

    A seed whose run fails is run again (``retries`` times, into a fresh folder); one that still
    fails is left out of the aggregate and named, with its error, in ``study["failed_seeds"]``
    (seed -> error text), so that one bad seed costs a study that seed, not the others. If no
    seed finishes, :class:`StudyError`. ``runner`` (tests) replaces the fleet run of one seed:
    a picklable callable with :func:`_one`'s arguments."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(seeds)))
    per_seed: dict[int, dict] = {}
    failed: dict[int, str] = {}
    tries = dict.fromkeys(seeds, 0)
    pool = worker_pool(jobs)

    def set_aside(s: int) -> None:
        """Keep a failed try's files (its logs say why) out of the study's ``seed-*`` runs."""
        seed_dir = out / f"seed-{s}"
        if seed_dir.exists():
            failed_dir = out / f"failed-seed-{s}-try{tries[s]}"
            shutil.rmtree(failed_dir, ignore_errors=True)
            seed_dir.rename(failed_dir)

    def submit(s: int):
        tries[s] += 1
        seed_dir = out / f"seed-{s}"
        return pool.submit(_interruptible, runner or _one, scenario, methods, s, str(seed_dir), fusion, sign,
                           agent_nice, lane_constraint, zenoh_mode, secure, lanelet2)

    try:
        futs = {submit(s): s for s in seeds}
        while futs:
            done = next(as_completed(futs))
            s = futs.pop(done)
            try:
                per_seed[s] = done.result()
            except BrokenProcessPool:  # a worker interrupted (SIGTERM): the study stops, below
                raise
            except Exception as exc:  # a seed whose run failed
                reason = f"{type(exc).__name__}: {exc}"
                set_aside(s)
                if tries[s] <= retries:
                    log.warning("seed %d failed (%s); running it again", s, reason)
                    futs[submit(s)] = s
                    continue
                log.warning("seed %d failed again (%s); the study goes on without it", s, reason)
                failed[s] = reason
            if progress:
                progress(len(per_seed) + len(failed), len(seeds), s)
    except BaseException:
        # interrupted: no new seed starts, then each worker stops its own fleet (SIGTERM -> its
        # cleanup) and the workers are joined
        procs = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            if proc.is_alive():
                os.kill(proc.pid, signal.SIGTERM)
        for proc in procs:
            proc.join(timeout=30)
        raise
    pool.shutdown(wait=True)
    if not per_seed:
        raise StudyError(
            "no seed of the study finished: " + "; ".join(f"seed {s}: {r}" for s, r in sorted(failed.items()))
        )
    study = aggregate(out, per_seed)
    study["failed_seeds"] = {str(s): r for s, r in sorted(failed.items())}
    study["fusion"] = fusion
    study["lane_constraint"] = lane_constraint
    from slcp.hw_emulation.scenario import load_scenario

    study["stance_draws"] = stance_check(load_scenario(scenario), sorted(per_seed))
    (out / "study.json").write_text(json.dumps(study, indent=2))
    return study


def aggregate(out: Path, per_seed: dict[int, dict]) -> dict:
    """Statistics over seeded runs (their metrics and estimate CSVs under ``out/seed-<S>``)."""
    seeds = sorted(per_seed)
    first = per_seed[seeds[0]]
    rmse = _rmse_cells(per_seed, seeds)
    return {"scenario": first["scenario"], "seeds": seeds, "rmse": rmse, "paired": _paired(per_seed, seeds, rmse),
            "anees": _anees(out, seeds), "first_stopped": _detection(per_seed, seeds)}


def _rmse_cells(per_seed: dict[int, dict], seeds: list[int]) -> dict:
    """Window -> vehicle -> method -> RMSE mean and sd over the seeds, bound and ANEES."""
    first = per_seed[seeds[0]]
    rmse: dict = {}
    for w in first["rmse"]:
        for vid in sorted({v for s in seeds for v in per_seed[s]["rmse"].get(w, {})}):
            for m in METHODS:
                cells = [per_seed[s]["rmse"][w][vid][m] for s in seeds
                         if m in per_seed[s]["rmse"].get(w, {}).get(vid, {})]
                if not cells:
                    continue
                vals = np.array([c["rmse_m"] for c in cells])
                rmse.setdefault(w, {}).setdefault(vid, {})[m] = {
                    "mean_rmse_m": float(vals.mean()), "sd_rmse_m": float(vals.std(ddof=1)) if len(vals) > 1 else 0.0,
                    "along_rmse_m": float(np.mean([c["along_rmse_m"] for c in cells])),
                    "cross_rmse_m": float(np.mean([c["cross_rmse_m"] for c in cells])), "n_seeds": len(cells)}
                cell = rmse[w][vid][m]
                if all("bound_rms_m" in c for c in cells):
                    cell["bound_rms_m"] = float(np.mean([c["bound_rms_m"] for c in cells]))
                    cell["sigma_below_bound"] = float(np.mean([c["sigma_below_bound"] for c in cells]))
                # the window's ANEES: every estimate in it, of every seed (a seed weighs by its
                # number of estimates), against the band of as many runs as held the window
                window_anees = _window_anees(cells)
                if window_anees is not None:
                    cell["anees"] = window_anees
    return rmse


def _window_anees(cells: list[dict]) -> dict | None:
    """A window's ANEES over every estimate of every seed (a seed weighs by its number of
    estimates), against the band of as many runs as held the window."""
    q = [(c["nees_h"], c.get("n", 1)) for c in cells if c.get("nees_h") is not None]
    q = [(a, k) for a, k in q if np.isfinite(a) and k > 0]
    if not q:
        return None
    lo, hi = anees_band(len(q))
    a = float(sum(a * k for a, k in q) / sum(k for _, k in q))
    return {"anees": a, "band": [lo, hi], "inside": bool(lo <= a <= hi)}


def _paired(per_seed: dict[int, dict], seeds: list[int], rmse: dict) -> dict:
    """Paired RMSE differences of the method pairs, per window and vehicle."""
    paired: dict = {}
    for w in rmse:
        for vid in rmse[w]:
            for m, ref in PAIRS:
                both = [s for s in seeds if {m, ref} <= set(per_seed[s]["rmse"].get(w, {}).get(vid, {}))]
                if both:
                    a, b = (np.array([per_seed[s]["rmse"][w][vid][k]["rmse_m"] for s in both]) for k in (m, ref))
                    paired.setdefault(w, {}).setdefault(vid, {})[f"{m} - {ref}"] = paired_difference(a, b)
    return paired


def _anees(out: Path, seeds: list[int]) -> dict:
    """Every vehicle and method's ANEES over the whole run, from the seeds' estimate files."""
    import csv

    nees: dict = {}
    for s in seeds:
        for path in sorted((out / f"seed-{s}" / "estimates").glob("*.csv")):
            with open(path, newline="") as fh:
                for row in csv.DictReader(fh):
                    q = float(row["nees_h"])
                    if np.isfinite(q):
                        nees.setdefault((path.stem, row["method"]), []).append(q)
    lo, hi = anees_band(len(seeds))
    anees = {f"{v}/{m}": {"anees": float(np.mean(q)), "band": [lo, hi], "inside": bool(lo <= np.mean(q) <= hi)}
             for (v, m), q in sorted(nees.items())}
    return anees


def _detection(per_seed: dict[int, dict], seeds: list[int]) -> dict:
    """First-stopped detection pooled over the seeds: precision, recall, latency."""
    det: dict = {}
    for s in seeds:
        for vid, ms in per_seed[s].get("first_stopped", {}).items():
            for m, d in ms.items():
                a = det.setdefault(f"{vid}/{m}", {"truth_s": 0.0, "claimed_s": 0.0, "wrong_s": 0.0, "covered_s": 0.0,
                                                  "latency_s": [], "_se_truth": 0.0, "_se_claimed": 0.0})
                for k in ("truth_s", "claimed_s", "wrong_s", "covered_s"):
                    a[k] += d[k]
                a["latency_s"] += [x for x in d["latency_s"] if x is not None]
                # squared error integrals, for RMS values pooled over the seeds
                a["_se_truth"] += (d.get("sl_rmse_truth_first_m") or 0.0) ** 2 * d["truth_s"]
                a["_se_claimed"] += (d.get("sl_rmse_claimed_m") or 0.0) ** 2 * d["covered_s"]
    for a in det.values():
        a["precision"] = 1.0 - a["wrong_s"] / a["claimed_s"] if a["claimed_s"] else None
        a["recall"] = a["covered_s"] / a["truth_s"] if a["truth_s"] else None
        a["mean_latency_s"] = float(np.mean(a["latency_s"])) if a["latency_s"] else None
        a["max_latency_s"] = float(np.max(a["latency_s"])) if a["latency_s"] else None
        a["sl_rmse_truth_first_m"] = float(np.sqrt(a["_se_truth"] / a["truth_s"])) if a["truth_s"] else None
        a["sl_rmse_claimed_m"] = float(np.sqrt(a["_se_claimed"] / a["covered_s"])) if a["covered_s"] else None
        for k in ("latency_s", "_se_truth", "_se_claimed"):
            del a[k]
    return det


def rebuild_study(out: Path) -> dict:
    """Re-aggregate a study directory from its seeds' metrics (``slcp report``)."""
    out = Path(out)
    old = json.loads((out / "study.json").read_text()) if (out / "study.json").is_file() else {}
    per_seed = {}
    for d in sorted(out.glob("seed-*")):
        try:
            per_seed[int(d.name.split("-", 1)[1])] = json.loads((d / "metrics.json").read_text())
        except (ValueError, OSError) as exc:
            raise ValueError(f"{d}: no readable metrics.json ({exc}); run `slcp report {d}` first") from None
    if not per_seed:
        raise ValueError(f"{out}: no seed-* runs")
    study = aggregate(out, per_seed)
    try:  # a study of a scenario file that has moved keeps the draws it had
        from slcp.hw_emulation.scenario import load_scenario

        study["stance_draws"] = stance_check(load_scenario(study["scenario"]), sorted(per_seed))
    except (ValueError, OSError):
        if "stance_draws" in old:
            study["stance_draws"] = old["stance_draws"]
    study["fusion"] = old.get("fusion", next(iter(per_seed.values())).get("fusion", "?"))
    study["lane_constraint"] = old.get("lane_constraint", next(iter(per_seed.values())).get("lane_constraint"))
    study["failed_seeds"] = {s: r for s, r in old.get("failed_seeds", {}).items() if int(s) not in per_seed}
    (out / "study.json").write_text(json.dumps(study, indent=2))
    return study
