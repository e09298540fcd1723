"""``slcp run``: a fleet on one machine over Zenoh on loopback.

The launcher opens a Zenoh session in router mode on ``tcp/127.0.0.1:<free port>`` and records
every estimate and diagnostics message (append-only JSON lines, flushed per batch). It starts the
emulator service and one agent process per vehicle (each a ``slcp`` subprocess in its own
session, logging to ``logs/``), waits for the emulator to finish, stops the agents with SIGTERM
(SIGKILL after a grace period), and never leaves a child behind (also on Ctrl-C). Then it
evaluates the recording against the truth and writes the run directory.

Run directory::

    config/agent-<vehicle>.toml      the agents' configurations
    logs/<process>.log               each process's log
    recorded/messages.jsonl          every recorded message, one JSON object per line
    estimates/<vehicle>.csv          time, method, lat, lon, h, velocity, attitude, sigma, errors
    metrics.json                     RMSE per window, vehicle and method; detection; counters
    report.md                        paper-style tables beside the paper's figures
    errors.png, map.png              error over time per vehicle and method; the map
"""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from agent.methods import METHODS
from agent.nav import earth
from hw_emulation.events import event_times, window_bounds
from hw_emulation.scenario import load_scenario
from hw_emulation.truth import build_truth
from transport import keys
from transport.codec import CodecError, decode
from transport.messages import Estimate

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _slcp(*args: str) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", *args]


def run_fleet(scenario: str = "paper-1", methods: tuple[str, ...] = METHODS, speed: float | None = None,
              seed: int = 0, out: Path = Path("runs/fleet"), progress=None) -> dict:
    """Run the fleet and return the metrics (also written to ``out``)."""
    scn = load_scenario(scenario)
    out = Path(out)
    for sub in ("config", "logs", "recorded", "estimates"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    vehicles = [v.id for v in scn.vehicles]
    configs = {}
    for vid in vehicles:
        p = out / "config" / f"agent-{vid}.toml"
        p.write_text(f'[agent]\nvehicle = "{vid}"\nscenario = "{scenario}"\nmethods = {json.dumps(list(methods))}\n\n'
                     f'[zenoh]\nmode = "peer"\nconnect = ["{endpoint}"]\n')
        configs[vid] = p
    wall0 = time.monotonic()
    stats = asyncio.run(_supervise(scenario, vehicles, configs, endpoint, speed, seed, out, progress))
    wall = time.monotonic() - wall0
    truth = build_truth(scn)
    metrics = evaluate_recording(truth, out / "recorded" / "messages.jsonl", out, methods)
    metrics["wall_s"] = wall
    metrics["processes"] = stats
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "report.md").write_text(report_markdown(scn, metrics))
    return metrics


async def _supervise(scenario, vehicles, configs, endpoint, speed, seed, out: Path, progress) -> dict:
    from transport.zenoh_bus import ZenohBus, ZenohConfig

    router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,)))
    procs: dict[str, subprocess.Popen] = {}
    logs = []
    stats: dict = {"exit_codes": {}, "recorded": 0, "codec_errors": 0}
    rec_file = open(out / "recorded" / "messages.jsonl", "a")
    est_sub = router.subscribe(keys.ROOT + "/estimate/**", 1_000_000)
    diag_sub = router.subscribe(keys.ROOT + "/diag/**", 100_000)
    latest_t: dict[str, float] = {}

    async def record(sub) -> None:
        while True:
            _, payload = await sub.get()
            batch = [payload]
            while not sub.queue.empty():
                batch.append(sub.queue.get_nowait()[1])
            for p in batch:
                try:
                    m = decode(p)
                except CodecError:
                    stats["codec_errors"] += 1
                    continue
                rec_file.write(json.dumps(_to_json(m)) + "\n")
                stats["recorded"] += 1
                if isinstance(m, Estimate):
                    latest_t[m.vehicle] = max(latest_t.get(m.vehicle, 0.0), m.t)
            rec_file.flush()

    tasks = [asyncio.create_task(record(est_sub)), asyncio.create_task(record(diag_sub))]
    try:
        for vid in vehicles:
            lf = open(out / "logs" / f"agent-{vid}.log", "w")
            logs.append(lf)
            procs[f"agent-{vid}"] = subprocess.Popen(_slcp("-v", "agent", "--vehicle", vid, "--config", str(configs[vid])),
                                                     stdout=lf, stderr=subprocess.STDOUT, start_new_session=True)
        lf = open(out / "logs" / "emulator.log", "w")
        logs.append(lf)
        emu_args = ["-v", "emulate", scenario, "--seed", str(seed), "--connect", endpoint]
        if speed:
            emu_args += ["--speed", str(speed)]
        emu = procs["emulator"] = subprocess.Popen(_slcp(*emu_args), stdout=lf, stderr=subprocess.STDOUT,
                                                   start_new_session=True)
        last = 0.0
        while emu.poll() is None:
            await asyncio.sleep(0.2)
            dead = [n for n, p in procs.items() if n != "emulator" and p.poll() is not None]
            if dead:
                raise RuntimeError(f"process(es) {dead} exited early; see {out / 'logs'}")
            if progress and time.monotonic() - last > 2.0:
                last = time.monotonic()
                progress("t=" + ", ".join(f"{v} {latest_t.get(v, 0.0):5.1f}s" for v in vehicles)
                         + f" | recorded {stats['recorded']}")
        await asyncio.sleep(0.5)  # last estimates in flight
    finally:
        _stop_all(procs)
        for t in tasks:
            t.cancel()
        rec_file.close()
        for lf in logs:
            lf.close()
        await router.close()
    stats["exit_codes"] = {n: p.returncode for n, p in procs.items()}
    return stats


def _stop_all(procs: dict[str, subprocess.Popen], grace: float = 10.0) -> None:
    for p in procs.values():
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace
    for p in procs.values():
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()


def _to_json(m) -> dict:
    out = {"type": type(m).__name__}
    for k, v in vars(m).items():
        out[k] = v.tolist() if isinstance(v, np.ndarray) else (v.hex() if isinstance(v, bytes) else v)
    return out


def evaluate_recording(truth, path: Path, out: Path, methods: tuple[str, ...]) -> dict:
    """RMSE per window, vehicle and method from the recorded estimates; writes estimate CSVs."""
    est: dict[tuple[str, str], list[dict]] = {}
    diags: dict[str, dict] = {}
    with open(path) as fh:
        for line in fh:
            r = json.loads(line)
            if r["type"] == "Estimate":
                est.setdefault((r["vehicle"], r["method"]), []).append(r)
            elif r["type"] == "Diagnostics":
                diags[r["source"]] = r["counters"]
    windows = window_bounds(truth)
    rows: dict = {w: {} for w in windows}
    series = {}
    for vid, vt in truth.vehicles.items():
        tr = vt.truth
        with open(out / "estimates" / f"{vid}.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["time_s", "method", "lat_deg", "lon_deg", "h_m", "vn_mps", "ve_mps", "vd_mps",
                        "roll_deg", "pitch_deg", "yaw_deg", "sigma_n_m", "sigma_e_m", "first_stopped",
                        "err_n_m", "err_e_m", "err_h_m", "err_along_m", "err_cross_m"])
            for m in methods:
                recs = sorted(est.get((vid, m), []), key=lambda r: r["t"])
                ts, eh = [], []
                for r in recs:
                    k = min(int(np.searchsorted(tr.t, r["t"] - 1e-9)), len(tr.t) - 1)
                    e = earth.ned_offset(*r["llh"], *tr.llh[k])
                    yaw = tr.euler[k, 2]
                    along = e[0] * math.cos(yaw) + e[1] * math.sin(yaw)
                    cross = -e[0] * math.sin(yaw) + e[1] * math.cos(yaw)
                    cov = np.array(r["cov_pos"])
                    w.writerow([f"{r['t']:.3f}", m, f"{math.degrees(r['llh'][0]):.9f}", f"{math.degrees(r['llh'][1]):.9f}",
                                f"{r['llh'][2]:.3f}", *(f"{x:.3f}" for x in r["v_ned"]),
                                *(f"{math.degrees(x):.3f}" for x in r["rpy"]),
                                f"{math.sqrt(cov[0][0]):.3f}", f"{math.sqrt(cov[1][1]):.3f}", int(r["first_stopped"]),
                                f"{e[0]:.3f}", f"{e[1]:.3f}", f"{math.hypot(e[0], e[1]):.3f}", f"{along:.3f}", f"{cross:.3f}"])
                    ts.append(r["t"])
                    eh.append((math.hypot(e[0], e[1]), along, cross))
                series[(vid, m)] = (np.array(ts), np.array(eh).reshape(-1, 3))
    try:
        from .plots import plot_run_errors, plot_scenario

        plot_run_errors(series, windows, methods, out / "errors.png",
                        f"{truth.scenario.name}: horizontal error per vehicle and method")
        plot_scenario(truth, out / "map.png", event_times(truth))
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        log.warning("matplotlib unavailable: no plots")
    for wname, (a, b) in windows.items():
        for (vid, m), (ts, eh) in series.items():
            sel = (ts >= a) & (ts <= b)
            if sel.any():
                rms = np.sqrt(np.mean(eh[sel] ** 2, axis=0))
                rows[wname].setdefault(vid, {})[m] = {"rmse_m": float(rms[0]), "along_rmse_m": float(rms[1]),
                                                      "cross_rmse_m": float(rms[2]), "n": int(sel.sum())}
    return {"scenario": truth.scenario.name, "events": event_times(truth), "windows": {k: list(v) for k, v in windows.items()},
            "rmse": rows, "estimates": {f"{v}/{m}": len(s[0]) for (v, m), s in series.items()}, "diagnostics": diags}


def report_markdown(scn, metrics: dict) -> str:
    lines = [f"# slcp run: {scn.name}", "", scn.description, "",
             "Horizontal RMSE [m] per window, vehicle and method (the paper's figure in brackets); "
             "along-track / cross-track RMSE below each value.", ""]
    for w, table in metrics["rmse"].items():
        lines += [f"## {w}", "", "| vehicle | " + " | ".join(METHODS) + " |", "|---" * (len(METHODS) + 1) + "|"]
        for vid, cells in sorted(table.items()):
            row = []
            for m in METHODS:
                c = cells.get(m)
                p = scn.paper_table.get(w, {}).get(vid, {}).get(m)
                if c is None:
                    row.append("–")
                else:
                    row.append(f"{c['rmse_m']:.2f}" + (f" [{p:.2f}]" if p is not None else "")
                               + f"<br>{c['along_rmse_m']:.2f} / {c['cross_rmse_m']:.2f}")
            lines.append(f"| {vid} | " + " | ".join(row) + " |")
        lines.append("")
    lines += ["## Events", "", ", ".join(f"{k} = {v:.1f} s" for k, v in metrics["events"].items()), "",
              "![errors](errors.png)", "", "![map](map.png)", ""]
    return "\n".join(lines)
