"""``slcp run``: a fleet on one machine over Zenoh on loopback.

The launcher opens a Zenoh session in router mode on ``tcp/127.0.0.1:<free port>`` and records
every estimate and diagnostics message (append-only JSON lines, flushed per batch). It starts the
emulator service and one agent process per vehicle (each a ``slcp`` subprocess in its own
session, logging to ``logs/``), waits for the emulator to finish, stops the agents with SIGTERM
(SIGKILL after a grace period), and never leaves a child behind (also on Ctrl-C). Then it
evaluates the recording against the truth and writes the run directory.

Run directory::

    config/agent-<vehicle>.toml      the agents' configurations
    keys/                            fleet CA, per-vehicle keys and certificates (beacon signing)
    logs/<process>.log               each process's log
    recorded/messages.jsonl          every recorded message, one JSON object per line
    estimates/<vehicle>.csv          time, method, lat, lon, h, velocity, attitude, sigma, errors
    metrics.json                     RMSE per window, vehicle and method; detection; counters
    report.md                        paper-style tables beside the paper's figures
    errors.png, map.png              error over time per vehicle and method; the map
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from agent.methods import DEFAULT_FUSION, METHODS, MethodSpec
from geo import earth
from hw_emulation.events import event_times, window_bounds
from hw_emulation.faults import PROCESS_FAULTS, load_faults
from hw_emulation.scenario import STANDING_WINDOW, load_scenario
from hw_emulation.truth import build_truth
from transport.security import create_fleet

from .bound import posterior_crlb
from .detection import score_first_stopped
from .processes import SUPERVISOR_ENV
from .progress import FleetProgress
from .recorder import Recorder

log = logging.getLogger(__name__)

#: How the agents and the emulator join the launcher's Zenoh router (see :func:`run_fleet`).
ZENOH_MODES = ("client", "peer")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _slcp(*args: str) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", *args]


def run_fleet(scenario: str = "paper-1", methods: tuple[str, ...] = METHODS, speed: float | None = None,
              seed: int = 0, out: Path = Path("runs/fleet"), progress=None, fusion: str = DEFAULT_FUSION,
              sign: bool = True, faults: Path | None = None, monitor=None, evaluate: bool = True,
              wait_agents: float = 20.0, agent_nice: int = 5, lane_constraint: bool = True,
              zenoh_mode: str = "client") -> dict:
    """Run the fleet and return the metrics (also written to ``out``).

    ``progress`` (optional) is called about twice a second with a
    :class:`deploy.progress.FleetProgress` (and once more before the evaluation). With ``sign``
    a fleet CA and per-vehicle keys are created in ``out/keys`` and every beacon is signed and
    verified. ``monitor`` (optional, see :class:`deploy.fleet_bench.FleetMonitor`) gets
    ``attach(bus, procs)`` once every process is started and ``sample(recorder)`` every 0.2 s.
    Without ``evaluate`` only the process statistics are returned (no truth, no metrics files).
    The emulator waits up to ``wait_agents`` seconds for every agent's liveliness. The agents run
    ``agent_nice`` steps below the normal scheduling priority (``nice``): on one machine the
    emulated sensors and radio, and the Zenoh router, stand for hardware that does not wait for
    the vehicles' computers, so they are served first when the CPUs are busy. Without
    ``lane_constraint`` the SL methods use the stop line only (the paper's), and so does the bound.

    ``zenoh_mode`` says how the agents and the emulator join the launcher's router: ``"client"``
    (default) sends every message through the router, one link per process; ``"peer"`` lets them
    dial each other as well (a full mesh of N²/2 links whose keep-alives alone cost a 50-agent
    fleet about a third of a core on one machine). Agents get Zenoh's light runtime
    (:data:`transport.zenoh_bus.LIGHT_CLIENT_RUNTIME`) unless ``ZENOH_RUNTIME`` is set."""
    if zenoh_mode not in ZENOH_MODES:
        raise ValueError(f"zenoh_mode must be one of {', '.join(ZENOH_MODES)}, got {zenoh_mode!r}")
    scn = load_scenario(scenario)
    schedule = load_faults(faults, {v.id for v in scn.vehicles}) if faults is not None else []
    out = Path(out)
    for sub in ("config", "logs", "recorded", "estimates"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    if faults is not None:  # the run keeps its own copy of the schedule
        (out / "config" / "faults.toml").write_text(Path(faults).read_text())
    # what `slcp report` needs to evaluate the recording of a run that never got to its evaluation
    source = str(Path(scenario).resolve()) if Path(scenario).is_file() else str(scenario)
    (out / "config" / "run.json").write_text(json.dumps({
        "scenario": source, "seed": seed, "methods": list(methods), "fusion": fusion,
        "lane_constraint": lane_constraint}, indent=2))
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    vehicles = [v.id for v in scn.vehicles]
    configs = {}
    security = ""
    if sign:
        create_fleet(out / "keys", vehicles, overwrite=True)
        security = '[security]\ntrust_dir = "../keys"\n\n'
    for vid in vehicles:
        p = out / "config" / f"agent-{vid}.toml"
        p.write_text(f'[agent]\nvehicle = "{vid}"\nscenario = "{scenario}"\nmethods = {json.dumps(list(methods))}\n'
                     f'fusion = "{fusion}"\nlane_constraint = {str(lane_constraint).lower()}\n\n{security}'
                     f'[zenoh]\nmode = "{zenoh_mode}"\nconnect = ["{endpoint}"]\n')
        configs[vid] = p
    wall0 = time.monotonic()
    stats = asyncio.run(_supervise(scenario, vehicles, configs, endpoint, speed, seed, out, progress,
                                   faults=schedule, monitor=monitor, wait_agents=wait_agents,
                                   agent_nice=agent_nice, zenoh_mode=zenoh_mode, end_t=scn.duration,
                                   title=scn.name))
    wall = time.monotonic() - wall0
    if not evaluate:
        return {"wall_s": wall, "processes": stats}
    if progress:
        progress(FleetProgress(scn.name, "evaluating", scn.duration, scn.duration, 0, len(vehicles),
                               stats["recorded"], wall))
    truth = build_truth(scn, stop_seed=seed)
    metrics = evaluate_recording(truth, out / "recorded" / "messages.jsonl", out, methods, schedule,
                                 lane_constraint)
    metrics["wall_s"] = wall
    metrics["seed"] = seed
    metrics["scenario_source"] = source
    metrics["fusion"] = fusion
    metrics["lane_constraint"] = lane_constraint
    metrics["processes"] = stats
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "report.md").write_text(report_markdown(scn, metrics))
    return metrics


def _check_resume_progressed(restarts: list[dict], t_now: float, how: str, out: Path) -> None:
    """Refuse to resume the emulator a second time at the same point: a resumed emulator that
    failed before the fleet's sensor time moved past its resume point stalls or crashes
    deterministically there, and another restart would only repeat it (and cost the watchdog's
    whole timeout each time)."""
    last = next((r for r in reversed(restarts) if r["process"] == "emulator"), None)
    if last is None or t_now > last["resumed_at_t_s"]:
        return
    raise RuntimeError(f"the emulator resumed at t={last['resumed_at_t_s']:.2f} s {how} before the fleet got past "
                       f"that time, as it had the first time: a failure that repeats at that point, so it is not "
                       f"restarted again (its log and thread stacks: {out / 'logs' / 'emulator.log'})")


async def _supervise(scenario, vehicles, configs, endpoint, speed, seed, out: Path, progress,
                     max_restarts: int = 3, faults: list | None = None, monitor=None,
                     wait_agents: float = 20.0, agent_nice: int = 0, zenoh_mode: str = "client",
                     end_t: float | None = None, stall_s: float = 30.0, exit_grace_s: float = 15.0,
                     title: str = "") -> dict:
    """Run the fleet's processes until the emulator has played the scenario; return their statistics.

    A process that dies is restarted (at most ``max_restarts`` times each; the emulator resumes
    at the fleet's sensor time). The emulator is also watched for a hang: with no estimate
    recorded for ``wait_agents + stall_s`` [s, wall] it is killed and resumed like a crashed
    one, and once the fleet's estimates have reached the scenario's end ``end_t`` [s, sensor
    time] it gets ``exit_grace_s`` [s, wall] of silence to exit before it is killed (counted in
    ``stats["emulator_killed_at_end"]``; its scenario was played, so the run goes on). A resumed
    emulator that fails again before the fleet gets past its resume point is not restarted a
    second time there: the run fails with what was seen (:func:`_check_resume_progressed`)."""
    from transport.zenoh_bus import LIGHT_CLIENT_RUNTIME, ZenohBus, ZenohConfig

    agent_env = {} if "ZENOH_RUNTIME" in os.environ else {"ZENOH_RUNTIME": LIGHT_CLIENT_RUNTIME}

    def agent_args(vid: str) -> list[str]:
        return _slcp("-v", "agent", "--vehicle", vid, "--config", str(configs[vid]), "--nice", str(agent_nice))

    router = ZenohBus(ZenohConfig(mode="router", listen=(endpoint,)))
    procs: dict[str, subprocess.Popen] = {}
    logs = []
    stats: dict = {"exit_codes": {}, "recorded": 0, "codec_errors": 0, "emulator_killed_at_end": False}
    rec_path = out / "recorded" / "messages.jsonl"
    rec_path.unlink(missing_ok=True)  # a new run starts a new recording
    rec = Recorder(rec_path)
    tasks = rec.start(router)
    restarts: list[dict] = []
    wall0 = time.monotonic()
    try:
        for vid in vehicles:
            lf = open(out / "logs" / f"agent-{vid}.log", "w")
            logs.append(lf)
            _spawn(procs, f"agent-{vid}", agent_args(vid), lf, agent_env)
        lf = open(out / "logs" / "emulator.log", "w")
        logs.append(lf)
        emu_args = ["-v", "emulate", scenario, "--seed", str(seed), "--connect", endpoint, "--mode", zenoh_mode,
                    "--wait-agents", f"{wait_agents:g}"]
        if faults:
            emu_args += ["--faults", str(out / "config" / "faults.toml")]
        pending = sorted((f for f in faults or [] if f.kind in PROCESS_FAULTS), key=lambda f: f.start)
        frozen: list[tuple[float, str]] = []  # (wall time to resume, process)
        if speed:
            emu_args += ["--speed", str(speed)]
        emu = _spawn(procs, "emulator", _slcp(*emu_args), lf)
        emu_started = time.monotonic()
        if monitor is not None:
            monitor.attach(router, procs)
        last = last_table = 0.0
        table = ""
        play0: float | None = None  # wall time of the first recorded estimate
        prev_diag: dict = {}
        silenced: float | None = None  # the watchdog killed the emulator after this long [s] of silence
        while True:
            silent = time.monotonic() - max(emu_started, max(rec.last_wall.values(), default=-math.inf))
            at_end = end_t is not None and max(rec.latest_t.values(), default=0.0) >= end_t - 1.0
            if emu.poll() is None and (silent > exit_grace_s if at_end else silent > wait_agents + stall_s):
                # a hung emulator (a run of the fault schedule once never finished; cause not traced)
                log.warning("the emulator has been silent for %.0f s%s; killing it (its stacks: logs/emulator.log)",
                            silent, " after the scenario's end" if at_end else "")
                await asyncio.to_thread(_dump_and_kill, emu)
                silenced = silent
                if at_end:
                    stats["emulator_killed_at_end"] = True
                    break
            if emu.poll() is not None:
                if emu.returncode == 0:
                    break
                # the emulator died: resume the scenario where the fleet is (sensor time)
                if sum(r["process"] == "emulator" for r in restarts) >= max_restarts:
                    raise RuntimeError(f"the emulator exited {max_restarts + 1} times; see {out / 'logs'}")
                now, rc = time.monotonic(), emu.returncode
                t_resume = max(rec.latest_t.values(), default=0.0)
                _check_resume_progressed(restarts, t_resume, f"was killed after {silenced:.0f} s of silence"
                                         if silenced is not None else f"exited with {rc}", out)
                silenced = None
                log.warning("the emulator exited with %s; restarting it at t=%.2f s", rc, t_resume)
                lf = open(out / "logs" / "emulator.log", "a")
                logs.append(lf)
                emu = _spawn(procs, "emulator", _slcp(*emu_args, "--start-at", f"{t_resume:.3f}"), lf)
                emu_started = time.monotonic()
                restarts.append({"process": "emulator", "exit_code": rc, "at_s": now - wall0, "_t": now,
                                 "rejoined_after_s": None, "resumed_at_t_s": t_resume})
            await asyncio.sleep(0.2)
            if monitor is not None:
                monitor.sample(rec)
            # process faults, at the fleet's sensor time (the newest estimate recorded)
            now_s = max(rec.latest_t.values(), default=0.0)
            while pending and pending[0].start <= now_s:
                f = pending.pop(0)
                p = procs.get("emulator" if f.kind == "emulator_kill" else f"agent-{f.vehicles[0]}")
                if p is None or p.poll() is not None:
                    continue
                log.warning("fault %s on %s at t=%.1f s", f.kind, ",".join(f.vehicles) or "emulator", now_s)
                os.kill(p.pid, signal.SIGSTOP if f.kind == "agent_freeze" else signal.SIGKILL)
                if f.kind == "agent_freeze":
                    frozen.append((time.monotonic() + f.end - f.start, f"agent-{f.vehicles[0]}"))
            for due, n in [x for x in frozen if x[0] <= time.monotonic()]:
                frozen.remove((due, n))
                if procs[n].poll() is None:
                    os.kill(procs[n].pid, signal.SIGCONT)
            for n in [n for n, p in procs.items() if n != "emulator" and p.poll() is not None]:
                # an agent died (crash, kill -9): start it again; it re-initialises from GNSS and
                # rejoins. Each restart is reported with the time until its first estimate.
                if sum(r["process"] == n for r in restarts) >= max_restarts:
                    raise RuntimeError(f"{n} exited {max_restarts + 1} times; see {out / 'logs'}")
                now, rc, vid = time.monotonic(), procs[n].returncode, n.removeprefix("agent-")
                log.warning("%s exited with %s; restarting it", n, rc)
                lf = open(out / "logs" / f"{n}.log", "a")
                logs.append(lf)
                _spawn(procs, n, agent_args(vid), lf, agent_env)
                restarts.append({"process": n, "exit_code": rc, "at_s": now - wall0, "_t": now,
                                 "rejoined_after_s": None})
            for r in restarts:  # an agent is back with its first estimate; the emulator with anyone's
                v = r["process"].removeprefix("agent-")
                seen = (max(rec.last_wall.values(), default=-math.inf) if r["process"] == "emulator"
                        else rec.last_wall.get(v, -math.inf))
                if r["rejoined_after_s"] is None and seen > r["_t"]:
                    r["rejoined_after_s"] = seen - r["_t"]
                    log.warning("%s rejoined %.2f s after its restart", r["process"], r["rejoined_after_s"])
            if progress and time.monotonic() - last > 0.5:
                last = time.monotonic()
                if time.monotonic() - last_table > 2.0:  # rates over two seconds
                    last_table, table = time.monotonic(), status_table(vehicles, rec.latest_t, rec.diag, prev_diag)
                    prev_diag = dict(rec.diag)
                now_w = time.monotonic()
                if play0 is None and rec.recorded:
                    play0 = now_w
                progress(
                    FleetProgress(
                        title or str(scenario),
                        "playing" if rec.recorded else "starting",
                        max(rec.latest_t.values(), default=0.0),
                        end_t,
                        sum(now_w - w < 3.0 for w in rec.last_wall.values()),
                        len(vehicles),
                        rec.recorded,
                        now_w - wall0,
                        table,
                        now_w - play0 if play0 is not None else 0.0,
                    )
                )
        await asyncio.sleep(0.5)  # last estimates in flight
    finally:
        # a second Ctrl-C while the children are stopped waits until they are (they run in
        # their own sessions: the terminal's signal never reaches them)
        with _termination_deferred():
            for p in procs.values():  # a frozen process would not see the SIGTERM
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(p.pid, signal.SIGCONT)
            _stop_all(procs)
            for t in tasks:
                t.cancel()
            rec.close()
            for lf in logs:
                lf.close()
        await router.close()
    stats["exit_codes"] = {n: p.returncode for n, p in procs.items()}
    stats["restarts"] = [{k: v for k, v in r.items() if not k.startswith("_")} for r in restarts]
    stats["recorded"], stats["codec_errors"] = rec.recorded, rec.codec_errors
    return stats


def status_table(vehicles: list[str], latest_t: dict[str, float], diag: dict, prev: dict) -> str:
    """The live status: per vehicle its sensor time, neighbours heard, beacon rates sent and
    received, first-stopped claim, ranges
    fused/rejected, and the drops (stale beacons, late measurements, bad payloads -- malformed,
    refused or misbehaving beacons, duplicates, time jumps --, queue drops).
    Rates are per second of sensor time between the last two diagnostics."""
    rows = [f"{'vehicle':8s} {'t [s]':>7s} {'nbrs':>4s} {'bcn tx/s':>8s} {'bcn rx/s':>8s} {'first':>5s} "
            f"{'ranges ok/rej':>13s} {'stale':>5s} {'late':>4s} {'bad':>4s} {'qdrop':>5s}"]
    for v in vehicles:
        _, c, st = diag.get(v, (None, {}, {}))
        _, pc, p_st = prev.get(v, (None, {}, {}))
        rate = {}
        for k in ("beacons_tx", "beacons_rx"):  # per second of sensor time
            dt = st.get("t", 0.0) - p_st.get("t", 0.0) if p_st else 0.0
            rate[k] = f"{(c.get(k, 0) - pc.get(k, 0)) / dt:8.1f}" if dt > 0 else f"{'-':>8s}"
        ok = sum(c.get(f"{m}_ranges", 0) for m in METHODS)
        rej = sum(c.get(f"{m}_ranges_rejected", 0) for m in METHODS)
        stale = sum(c.get(f"{m}_stale", 0) for m in METHODS)
        late = c.get("seq_late_dropped", 0)
        bad = c.get("codec_errors", 0) + sum(
            v2
            for k2, v2 in c.items()
            if k2.startswith(("rejected_", "beacon_", "duplicate_")) or k2.endswith("_time_jump")
        )
        qdrop = sum(v2 for k2, v2 in c.items() if k2.startswith("queue_dropped_"))
        first = ",".join(m for m in st.get("first_stopped", []))
        rows.append(
            f"{v:8s} {latest_t.get(v, 0.0):7.1f} {st.get('neighbours', 0):4d} {rate['beacons_tx']} "
            f"{rate['beacons_rx']} {first or '-':>5s} {f'{ok}/{rej}':>13s} {stale:5d} {late:4d} {bad:4d} {qdrop:5d}"
        )
    return "\n".join(rows)


def interrupt_on_termination() -> None:
    """Make SIGTERM and SIGHUP behave like Ctrl-C (KeyboardInterrupt) in this process, so that a
    launcher killed politely still stops its children (the default handlers exit at once,
    skipping every ``finally``)."""

    def handler(signum, frame):  # noqa: ARG001 - signal handler signature
        raise KeyboardInterrupt(f"signal {signum}")

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, handler)


@contextlib.contextmanager
def _termination_deferred():
    """Hold SIGINT/SIGTERM/SIGHUP back for the duration of the block and re-raise the first one as
    KeyboardInterrupt afterwards. A signal that arrived while ``Popen`` waited for the child's
    ``exec`` would otherwise abandon a child that exists but is not yet in the process table we
    clean up. Outside the main thread (where handlers cannot be set) the block runs unguarded."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    old = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if pending:
            raise KeyboardInterrupt(f"signal {pending[0]}")


def _spawn(procs: dict[str, subprocess.Popen], name: str, args: list[str], log,
           env: dict[str, str] | None = None) -> subprocess.Popen:
    """Start ``args`` in its own session with output to ``log`` (and ``env`` added to this
    process's environment) and enter it in ``procs`` before any termination signal can
    interrupt (see `_termination_deferred`)."""
    with _termination_deferred():
        p = procs[name] = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                           env={**os.environ, **(env or {}), SUPERVISOR_ENV: str(os.getpid())})
    return p


def _dump_and_kill(p: subprocess.Popen, dump_wait: float = 0.5) -> None:
    """SIGKILL a hung child's process group, after SIGUSR1 (every ``slcp`` process then writes
    its threads' Python stacks to its log, :func:`deploy.cli.main`) and ``dump_wait`` [s]."""
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGUSR1)
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=dump_wait)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(p.pid, signal.SIGKILL)
    p.wait()


def _stop_all(procs: dict[str, subprocess.Popen], grace: float = 10.0) -> None:
    for p in procs.values():
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + grace
    for name, p in procs.items():
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s of SIGTERM; killing it (its stacks: its log)", name, grace)
            _dump_and_kill(p)


def lane_keeping_label(lane_constraint: bool | None) -> str:
    """", lane-keeping on|off" for a report's title ("" when a run does not say)."""
    return {True: ", lane-keeping on", False: ", lane-keeping off"}.get(lane_constraint, "")


def evaluate_recording(truth, path: Path, out: Path, methods: tuple[str, ...], faults: list | None = None,
                       lane_constraint: bool = True) -> dict:
    """RMSE per window, vehicle and method from the recorded estimates; writes estimate CSVs.
    ``lane_constraint`` says whether the SL methods kept to the lanes (for the bound).
    With a fault schedule, each fault's window is shaded on the plot and its recovery measured
    (:func:`fault_recovery`)."""
    est: dict[tuple[str, str], list[dict]] = {}
    diags: dict[str, dict] = {}
    bad_lines = 0
    with open(path) as fh:
        for line in fh:
            try:
                r = json.loads(line)
            except json.JSONDecodeError:  # e.g. a line cut short when a recorder was killed
                bad_lines += 1
                continue
            if r["type"] == "Estimate":
                est.setdefault((r["vehicle"], r["method"]), []).append(r)
            elif r["type"] == "Diagnostics":
                diags[r["source"]] = r["counters"]
    windows = window_bounds(truth)
    bound = posterior_crlb(truth, tuple(methods), lane_constraint=lane_constraint)
    rows: dict = {w: {} for w in windows}
    series = {}
    extra = {}
    standing: dict[tuple[str, str], np.ndarray] = {}
    sig_h = {}
    for vid, vt in truth.vehicles.items():
        tr = vt.truth
        with open(out / "estimates" / f"{vid}.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["time_s", "method", "lat_deg", "lon_deg", "h_m", "vn_mps", "ve_mps", "vd_mps",
                        "roll_deg", "pitch_deg", "yaw_deg", "sigma_n_m", "sigma_e_m", "cov_ne_m2", "first_stopped",
                        "err_n_m", "err_e_m", "err_h_m", "err_along_m", "err_cross_m", "nees_h"])
            for m in methods:
                recs = sorted(est.get((vid, m), []), key=lambda r: r["t"])
                ts, eh, nees, claim, truth_first, stands = [], [], [], [], [], []
                for r in recs:
                    k = min(int(np.searchsorted(tr.t, r["t"] - 1e-9)), len(tr.t) - 1)
                    e = earth.ned_offset(*r["llh"], *tr.llh[k])
                    yaw = tr.euler[k, 2]
                    along = e[0] * math.cos(yaw) + e[1] * math.sin(yaw)
                    cross = -e[0] * math.sin(yaw) + e[1] * math.cos(yaw)
                    cov = np.array(r["cov_pos"])
                    try:
                        q = float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2]))
                    except np.linalg.LinAlgError:
                        q = math.inf
                    w.writerow(
                        [
                            f"{r['t']:.3f}",
                            m,
                            f"{math.degrees(r['llh'][0]):.9f}",
                            f"{math.degrees(r['llh'][1]):.9f}",
                            f"{r['llh'][2]:.3f}",
                            *(f"{x:.3f}" for x in r["v_ned"]),
                            *(f"{math.degrees(x):.3f}" for x in r["rpy"]),
                            f"{math.sqrt(cov[0][0]):.3f}",
                            f"{math.sqrt(cov[1][1]):.3f}",
                            f"{cov[0][1]:.4f}",
                            int(r["first_stopped"]),
                            f"{e[0]:.3f}",
                            f"{e[1]:.3f}",
                            f"{math.hypot(e[0], e[1]):.3f}",
                            f"{along:.3f}",
                            f"{cross:.3f}",
                            f"{q:.4f}",
                        ]
                    )
                    ts.append(r["t"])
                    eh.append((math.hypot(e[0], e[1]), along, cross))
                    nees.append(q)
                    claim.append(bool(r["first_stopped"]))
                    truth_first.append(bool(vt.first_stopped[k]))
                    stands.append(bool(vt.stopped[k]))
                series[(vid, m)] = (np.array(ts), np.array(eh).reshape(-1, 3))
                extra[(vid, m)] = (np.array(nees), np.array(claim, bool), np.array(truth_first, bool))
                standing[(vid, m)] = np.array(stands, bool)
                sig_h[(vid, m)] = np.sqrt([r["cov_pos"][0][0] + r["cov_pos"][1][1] for r in recs])
    try:
        from .plots import plot_run_errors, plot_scenario

        plot_run_errors(series, windows, methods, out / "errors.png",
                        f"{truth.scenario.name}: horizontal error per vehicle and method", sig_h, bound,
                        faults=faults)
        shown = next((m for m in ("SL-CP", "CP", "SL-SP", "SP") if m in methods), None)
        plot_scenario(truth, out / "map.png", event_times(truth), map_estimates(est, truth, shown), shown)
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        log.warning("matplotlib unavailable: no plots")
    for (vid, m), (ts, eh) in series.items():
        # the scenario's windows, then the vehicle's own: the times it truly stands still
        masks = [(wname, (ts >= a) & (ts <= b)) for wname, (a, b) in windows.items()]
        for wname, sel in masks + [(STANDING_WINDOW, standing[(vid, m)])]:
            if sel.any():
                rms = np.sqrt(np.mean(eh[sel] ** 2, axis=0))
                nees = extra[(vid, m)][0][sel]
                lim = bound.at(m, vid, ts[sel])
                rows.setdefault(wname, {}).setdefault(vid, {})[m] = {
                    "rmse_m": float(rms[0]), "along_rmse_m": float(rms[1]), "cross_rmse_m": float(rms[2]),
                    "n": int(sel.sum()), "nees_h": float(np.mean(nees)), "bound_rms_m": float(np.sqrt(np.mean(lim**2))),
                    "sigma_below_bound": float(np.mean(sig_h[(vid, m)][sel] < lim * 0.99))}
    detection = {}
    for (vid, m), (_nees, claim, truth_first) in extra.items():
        if MethodSpec.of(m).stop_line and (claim.any() or truth_first.any()):
            detection.setdefault(vid, {})[m] = score_first_stopped(series[(vid, m)][0], truth_first, claim,
                                                                   series[(vid, m)][1][:, 0])
    fault_rows = [fault_recovery(f, series, sorted(truth.vehicles)) for f in faults or []]
    return {
        "scenario": truth.scenario.name,
        "events": event_times(truth),
        "windows": {k: list(v) for k, v in windows.items()},
        "faults": fault_rows,
        "rmse": rows,
        "first_stopped": detection,
        "unreadable_lines": bad_lines,
        "estimates": {f"{v}/{m}": len(s[0]) for (v, m), s in series.items()},
        "diagnostics": diags,
    }


def fault_recovery(fault, series: dict, vehicles: list[str], before: float = 5.0) -> dict:
    """A fault's effect on the affected vehicles' horizontal error, per method: the mean over
    ``before`` seconds before it, the maximum from its start to 10 s after its end, and the
    recovery time: from its end until the error, past that maximum, is back within
    max(1.2 × before, before + 0.3 m) (None if it never is)."""
    hit = list(fault.vehicles) or vehicles
    out = {"kind": fault.kind, "start_s": fault.start, "end_s": fault.end, "vehicles": list(fault.vehicles),
           "effect": {}}
    for (vid, m), (ts, eh) in series.items():
        if vid not in hit or not len(ts):
            continue
        pre = eh[(ts >= fault.start - before) & (ts < fault.start), 0]
        during = (ts >= fault.start) & (ts <= fault.end + 10.0)
        if not pre.size or not during.any():
            continue
        base = float(np.mean(pre))
        ok = max(1.2 * base, base + 0.3)
        idx = np.flatnonzero(during)
        peak = idx[int(np.argmax(eh[idx, 0]))]
        after = np.flatnonzero((ts >= max(fault.end, ts[peak])) & (eh[:, 0] <= ok))
        if eh[peak, 0] <= ok:
            recovery: float | None = 0.0  # never left the band
        else:
            recovery = max(float(ts[after[0]] - fault.end), 0.0) if after.size else None
        out["effect"].setdefault(vid, {})[m] = {"before_m": base, "max_m": float(eh[peak, 0]),
                                                "recovery_s": recovery}
    return out


def report_markdown(scn, metrics: dict) -> str:
    """The run's report: paper-style RMSE tables with along/cross-track split and NEES, the
    first-stopped detection scores, events and plots."""
    fusion = metrics.get("fusion", "split-ci")  # runs from before source CI did not record it
    lane = lane_keeping_label(metrics.get("lane_constraint"))
    lines = [
        f"# slcp run: {scn.name} (seed {metrics.get('seed', '?')}, fusion `{fusion}`{lane})",
        "",
        scn.description,
        "",
        "Horizontal RMSE [m] per window, vehicle and method, the paper's figure in brackets. Below each value: "
        "along-track / cross-track RMSE [m]; the mean horizontal NEES (2 for a consistent filter); the "
        "posterior Cramér-Rao bound (RMS over the window) and the share of time the reported σ is below it "
        "(an unbiased filter whose σ is below the bound is overconfident).",
        "",
    ]
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
                    row.append(
                        f"{c['rmse_m']:.2f}"
                        + (f" [{p:.2f}]" if p is not None else "")
                        + f"<br>{c['along_rmse_m']:.2f} / {c['cross_rmse_m']:.2f}"
                        + f"<br>NEES {c.get('nees_h', float('nan')):.1f}"
                        + f"<br>bound {c.get('bound_rms_m', float('nan')):.2f}, "
                        + f"σ<bound {100 * c.get('sigma_below_bound', 0):.0f} %"
                    )
            lines.append(f"| {vid} | " + " | ".join(row) + " |")
        lines.append("")
    det = metrics.get("first_stopped", {})
    if det:
        lines += ["## First-stopped detection", "",
                  "Against the emulator's truth (a claim within 0.3 s of a true first-stopped interval counts as "
                  "correct). SL RMSE: the stop-line method's horizontal error over the whole true interval "
                  "(detection latency included) and over its claimed part.", "",
                  "| vehicle | method | truly first [s] | claimed [s] | wrong [s] | precision | recall | latency [s] "
                  "| SL RMSE whole / claimed [m] |", "|---" * 9 + "|"]
        for vid, ms in sorted(det.items()):
            for m, d in ms.items():
                def f(x, fmt="{:.3f}"):
                    return "–" if x is None else fmt.format(x)
                lat = ", ".join("–" if x is None else f"{x:.1f}" for x in d["latency_s"]) or "–"
                lines.append(
                    f"| {vid} | {m} | {d['truth_s']:.1f} | {d['claimed_s']:.1f} | {d['wrong_s']:.1f} | "
                    f"{f(d['precision'])} | {f(d['recall'])} | {lat} | "
                    f"{f(d.get('sl_rmse_truth_first_m'), '{:.2f}')} / {f(d.get('sl_rmse_claimed_m'), '{:.2f}')} |"
                )
        lines.append("")
    if metrics.get("faults"):
        lines += ["## Faults", "", "Error of each affected vehicle: mean over 5 s before the fault, maximum until 10 s "
                  "after it, and the time from its end until the error, past that maximum, is back within "
                  "max(1.2 × before, before + 0.3 m).",
                  "", "| fault | window [s] | vehicle | method | before [m] | max [m] | recovery [s] |",
                  "|---|---|---|---|---|---|---|"]
        for f in metrics["faults"]:
            who = ",".join(f["vehicles"]) or "all"
            for vid, per in f["effect"].items():
                for m, e in per.items():
                    rec = "never" if e["recovery_s"] is None else f"{e['recovery_s']:.1f}"
                    lines.append(f"| {f['kind']} ({who}) | {f['start_s']:.1f}–{f['end_s']:.1f} | {vid} | {m} | "
                                 f"{e['before_m']:.2f} | {e['max_m']:.2f} | {rec} |")
        lines.append("")
    restarts = metrics.get("processes", {}).get("restarts", [])
    if restarts:
        lines += [
            "## Process faults",
            "",
            "| process | exit code | at [s wall] | rejoined after [s] |",
            "|---|---|---|---|",
        ]
        for r in restarts:
            rj = "never" if r["rejoined_after_s"] is None else f"{r['rejoined_after_s']:.2f}"
            lines.append(f"| {r['process']} | {r['exit_code']} | {r['at_s']:.1f} | {rj} |")
        lines.append("")
    lines += ["## Events", "", ", ".join(f"{k} = {v:.1f} s" for k, v in metrics["events"].items()), "",
              "![errors](errors.png)", "", "![map](map.png)", ""]
    return "\n".join(lines)


def map_estimates(est: dict, truth, method: str | None) -> dict:
    """The recorded estimates of ``method`` per vehicle in the map frame, for the map:
    {vehicle: (t, north/east (n, 2), north/east covariance (n, 2, 2))}."""
    out = {}
    o = truth.scenario.origin_llh
    for vid in truth.vehicles:
        recs = sorted(est.get((vid, method), []), key=lambda r: r["t"])
        if not recs:
            continue
        ne = np.array([earth.ned_offset(*r["llh"], *o)[:2] for r in recs])
        cov = np.array([np.asarray(r["cov_pos"], float)[:2, :2] for r in recs])
        out[vid] = (np.array([r["t"] for r in recs]), ne, cov)
    return out


def rebuild_report(run_dir: Path) -> dict:
    """Re-evaluate a single run directory from its recording (``slcp report``)."""
    import tomllib

    run_dir = Path(run_dir)
    mpath = run_dir / "metrics.json"
    rec = run_dir / "recorded" / "messages.jsonl"
    if not rec.is_file():
        raise ValueError(f"{run_dir}: not a run directory (no recorded/messages.jsonl)")
    old: dict = {}
    if mpath.is_file():
        try:
            old = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{mpath}: unreadable metrics ({exc})") from None
    run_cfg = run_dir / "config" / "run.json"
    if run_cfg.is_file():  # what the run was started with: the scenario's file, not only its name
        try:
            started = json.loads(run_cfg.read_text())
            old.update({k: v for k, v in started.items() if k in ("scenario", "methods") or k not in old})
        except (json.JSONDecodeError, AttributeError, TypeError) as exc:
            raise ValueError(f"{run_cfg}: unreadable ({exc})") from None
    name = old.get("scenario")
    for cfg in sorted((run_dir / "config").glob("agent-*.toml")) if name is None else ():
        try:  # a run that stopped before its evaluation: the agents' configs name the scenario
            agent = tomllib.loads(cfg.read_text()).get("agent", {})
        except (OSError, tomllib.TOMLDecodeError):
            continue
        name, old["fusion"] = agent.get("scenario"), agent.get("fusion", "split-ci")
        old["lane_constraint"] = agent.get("lane_constraint", True)
        break
    if not isinstance(name, str):
        raise ValueError(f"{run_dir}: cannot tell the scenario (no metrics.json or config/agent-*.toml)")
    scn = load_scenario(name)
    (run_dir / "estimates").mkdir(exist_ok=True)
    fpath = run_dir / "config" / "faults.toml"
    schedule = load_faults(fpath, {v.id for v in scn.vehicles}) if fpath.exists() else []
    seed = old.get("seed")
    truth = build_truth(scn, stop_seed=seed if isinstance(seed, int) and seed >= 0 else None)
    methods = tuple(m for m in old.get("methods", METHODS) if m in METHODS) or METHODS  # the run's own
    metrics = evaluate_recording(truth, rec, run_dir, methods, schedule, old.get("lane_constraint", True) is not False)
    for k in ("wall_s", "seed", "fusion", "lane_constraint", "processes"):
        if k in old:
            metrics[k] = old[k]
    metrics["scenario_source"] = name
    mpath.write_text(json.dumps(metrics, indent=2))
    (run_dir / "report.md").write_text(report_markdown(scn, metrics))
    return metrics
