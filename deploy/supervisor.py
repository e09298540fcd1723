"""The fleet's supervisor: starts the agents and the emulator, keeps them alive, applies the
process faults, and stops every child (also on Ctrl-C).

Every process is a ``slcp`` subprocess in its own session, logging to ``<run>/logs/``; the
supervisor's Zenoh router records every estimate and diagnostics message as it goes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from slcp.agent.methods import METHODS
from slcp.hw_emulation.faults import PROCESS_FAULTS

from .processes import SUPERVISOR_ENV
from .progress import FleetProgress
from .recorder import Recorder

log = logging.getLogger(__name__)

#: [s] how far before the scenario's start and after its end a recorded message's time may lie
RECORD_MARGIN_S = 60.0


def _slcp(*args: str) -> list[str]:
    return [sys.executable, "-m", "slcp.deploy.cli", *args]


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


async def supervise(scenario, vehicles, configs, endpoint, speed, seed, out: Path, progress,
                    max_restarts: int = 3, faults: list | None = None, monitor=None,
                    wait_agents: float = 20.0, agent_nice: int = 0, zenoh_mode: str = "client",
                    end_t: float | None = None, stall_s: float = 30.0, exit_grace_s: float = 15.0,
                    title: str = "", fleet_dir: Path | None = None,
                    sinks: list | tuple = (), agent_args: tuple[str, ...] = ()) -> dict:
    """Run the fleet's processes until the emulator has played the scenario; return their statistics.

    A process that dies is restarted (at most ``max_restarts`` times each; the emulator resumes
    at the fleet's sensor time). The emulator is also watched for a hang: with no estimate
    recorded for ``wait_agents + stall_s`` [s, wall] it is killed and resumed like a crashed
    one, and once the fleet's estimates have reached the scenario's end ``end_t`` [s, sensor
    time] it gets ``exit_grace_s`` [s, wall] of silence to exit before it is killed (counted in
    ``stats["emulator_killed_at_end"]``; its scenario was played, so the run goes on). A resumed
    emulator that fails again before the fleet gets past its resume point is not restarted a
    second time there: the run fails with what was seen (:func:`_check_resume_progressed`).

    With ``fleet_dir`` (the run's keys) the router is the fleet's: mutual TLS and the access
    control list (:func:`deploy.zenoh_security.router_config`), and the emulator joins with its
    certificate; the agents' configurations say the same for them. ``agent_args`` are added to
    every agent's command line."""
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    from .zenoh_security import router_config

    def open_router() -> ZenohBus:
        return ZenohBus(router_config(fleet_dir, (endpoint,)) if fleet_dir is not None
                        else ZenohConfig(mode="router", listen=(endpoint,)))

    sup = _Supervisor(vehicles, configs, out, progress, max_restarts, faults or [], monitor, wait_agents,
                      agent_nice, end_t, stall_s, exit_grace_s, title or str(scenario), sinks, agent_args)
    sup.open_router(open_router)
    emu_args = ["-v", "emulate", scenario, "--seed", str(seed), "--connect", endpoint, "--mode", zenoh_mode,
                "--wait-agents", f"{wait_agents:g}"]
    if fleet_dir is not None:
        emu_args += ["--fleet", str(fleet_dir)]
    if faults:
        emu_args += ["--faults", str(out / "config" / "faults.toml")]
    if speed:
        emu_args += ["--speed", str(speed)]
    try:
        sup.start(emu_args)
        if monitor is not None:
            monitor.attach(sup.router, sup.procs, endpoint)
        while not await sup.tick():
            pass
        await asyncio.sleep(0.5)  # last estimates in flight
    finally:
        sup.stop()
        if sup.router is not None:
            await sup.router.close()
    return sup.statistics()


class _Supervisor:
    """The state of one supervised run; :meth:`tick` is one look at the processes (0.2 s)."""

    def __init__(self, vehicles, configs, out: Path, progress, max_restarts: int, faults: list, monitor,
                 wait_agents: float, agent_nice: int, end_t: float | None, stall_s: float,
                 exit_grace_s: float, title: str, sinks: list | tuple = (),
                 agent_args: tuple[str, ...] = ()) -> None:
        from slcp.transport.zenoh_bus import LIGHT_CLIENT_RUNTIME

        self.vehicles, self.configs, self.out = vehicles, configs, out
        self.progress, self.max_restarts, self.monitor = progress, max_restarts, monitor
        self.wait_agents, self.agent_nice, self.end_t = wait_agents, agent_nice, end_t
        self.stall_s, self.exit_grace_s, self.title = stall_s, exit_grace_s, title
        self.agent_args = tuple(agent_args)
        self.agent_env = {} if "ZENOH_RUNTIME" in os.environ else {"ZENOH_RUNTIME": LIGHT_CLIENT_RUNTIME}
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: list = []
        self.stats: dict = {"exit_codes": {}, "recorded": 0, "codec_errors": 0, "rejected": {},
                            "emulator_killed_at_end": False}
        rec_path = out / "recorded" / "messages.jsonl"
        rec_path.unlink(missing_ok=True)  # a new run starts a new recording
        # an estimate's time can set the fleet's clock (faults, resume): only the scenario's, with
        # a margin for the agents' alignment and hold-back
        self.rec = Recorder(rec_path, (-RECORD_MARGIN_S, (end_t if end_t is not None else math.inf) + RECORD_MARGIN_S),
                            sinks=sinks)
        self.restarts: list[dict] = []
        self.wall0 = time.monotonic()
        self.pending = sorted((f for f in faults if f.kind in PROCESS_FAULTS), key=lambda f: f.start)
        self.missed: list = []  #: process faults that came due with their process not running
        self.frozen: list[tuple[float, str]] = []  # (wall time to resume, process)
        self.last = self.last_table = 0.0
        self.table = ""
        self.play0: float | None = None  # wall time of the first recorded estimate
        self.prev_diag: dict = {}
        self.silenced: float | None = None  # the watchdog killed the emulator after this long [s] of silence
        self.emu_args: list[str] = []
        self.router = None  # the Zenoh router (this process's session), None while it is down
        self.rec_tasks: list[asyncio.Task] = []
        self._router_factory = None
        self._router_down: tuple[float, float] | None = None  # (wall time to reopen, fleet time it went down)

    def open_router(self, factory) -> None:
        """Open the router with ``factory()`` and record what it carries."""
        self._router_factory = factory
        self.router = factory()
        self.rec_tasks = self.rec.start(self.router)

    async def _cycle_router(self) -> None:
        """A ``router_restart`` fault: the router was closed; reopen it when due. Clients (the
        agents, the emulator) reconnect by themselves and declare their liveliness again; what
        was published while it was down is lost, as on a real network."""
        if self._router_down is None or time.monotonic() < self._router_down[0]:
            return
        after_t = self._router_down[1]
        self._router_down = None
        self.open_router(self._router_factory)
        now = time.monotonic()
        log.warning("router reopened at t=%.1f s", after_t)
        self.restarts.append({"process": "router", "exit_code": "stopped", "at_s": now - self.wall0, "_t": now,
                              "_after_t": after_t, "rejoined_after_s": None})

    async def _stop_router(self, down_s: float) -> None:
        for t in self.rec_tasks:
            t.cancel()
        self.rec.flush()
        if self.router is not None:
            await self.router.close()
        self.router = None
        self._router_down = (time.monotonic() + down_s, self._fleet_t())

    def _log(self, name: str, mode: str = "w"):
        lf = open(self.out / "logs" / f"{name}.log", mode)
        self.logs.append(lf)
        return lf

    def _agent_args(self, vid: str) -> list[str]:
        return _slcp("-v", "agent", "--vehicle", vid, "--config", str(self.configs[vid]),
                     "--nice", str(self.agent_nice), *self.agent_args)

    def start(self, emu_args: list[str]) -> None:
        for vid in self.vehicles:
            _spawn(self.procs, f"agent-{vid}", self._agent_args(vid), self._log(f"agent-{vid}"), self.agent_env)
        self.emu_args = emu_args
        self.emu = _spawn(self.procs, "emulator", _slcp(*emu_args), self._log("emulator"))
        self.emu_started = time.monotonic()

    def _fleet_t(self) -> float:
        """The fleet's sensor time: the newest estimate recorded [s]."""
        return max(self.rec.latest_t.values(), default=0.0)

    async def tick(self) -> bool:
        """Watch, restart, apply faults and report; True once the emulator has finished."""
        if await self._watch_emulator():
            return True
        await asyncio.sleep(0.2)
        if self.monitor is not None:
            self.monitor.sample(self.rec)
        for f in self._apply_faults():
            await self._stop_router(f.end - f.start)
        await self._cycle_router()
        self._restart_agents()
        self._note_rejoins()
        self._report()
        return False

    async def _watch_emulator(self) -> bool:
        """Kill a silent emulator, resume a dead one; True when it finished its scenario."""
        rec, emu = self.rec, self.emu
        silent = time.monotonic() - max(self.emu_started, max(rec.last_wall.values(), default=-math.inf))
        at_end = self.end_t is not None and self._fleet_t() >= self.end_t - 1.0
        if emu.poll() is None and (silent > self.exit_grace_s if at_end else silent > self.wait_agents + self.stall_s):
            # a hung emulator (a run of the fault schedule once never finished; cause not traced)
            log.warning("the emulator has been silent for %.0f s%s; killing it (its stacks: logs/emulator.log)",
                        silent, " after the scenario's end" if at_end else "")
            await asyncio.to_thread(_dump_and_kill, emu)
            self.silenced = silent
            if at_end:
                self.stats["emulator_killed_at_end"] = True
                return True
        if emu.poll() is None:
            return False
        if emu.returncode == 0:
            return True
        self._resume_emulator()
        return False

    def _resume_emulator(self) -> None:
        """The emulator died: resume the scenario where the fleet is (sensor time)."""
        if sum(r["process"] == "emulator" for r in self.restarts) >= self.max_restarts:
            raise RuntimeError(f"the emulator exited {self.max_restarts + 1} times; see {self.out / 'logs'}")
        now, rc = time.monotonic(), self.emu.returncode
        t_resume = self._fleet_t()
        _check_resume_progressed(self.restarts, t_resume, f"was killed after {self.silenced:.0f} s of silence"
                                 if self.silenced is not None else f"exited with {rc}", self.out)
        self.silenced = None
        log.warning("the emulator exited with %s; restarting it at t=%.2f s", rc, t_resume)
        self.emu = _spawn(self.procs, "emulator", _slcp(*self.emu_args, "--start-at", f"{t_resume:.3f}"),
                          self._log("emulator", "a"))
        self.emu_started = time.monotonic()
        self.restarts.append({"process": "emulator", "exit_code": rc, "at_s": now - self.wall0, "_t": now,
                              "_after_t": t_resume, "rejoined_after_s": None, "resumed_at_t_s": t_resume})

    def _apply_faults(self) -> list:
        """Process faults, at the fleet's sensor time; frozen processes thawed when due. Returns
        the router faults now due (:meth:`_stop_router` takes them)."""
        now_s = self._fleet_t()
        router_faults = []
        while self.pending and self.pending[0].start <= now_s:
            f = self.pending.pop(0)
            if f.kind == "router_restart":
                if self.router is not None:
                    log.warning("fault router_restart at t=%.1f s (down %.1f s)", now_s, f.end - f.start)
                    router_faults.append(f)
                continue
            p = self.procs.get("emulator" if f.kind == "emulator_kill" else f"agent-{f.vehicles[0]}")
            if p is None or p.poll() is not None:
                self.missed.append(f)
                continue
            log.warning("fault %s on %s at t=%.1f s", f.kind, ",".join(f.vehicles) or "emulator", now_s)
            os.kill(p.pid, signal.SIGSTOP if f.kind == "agent_freeze" else signal.SIGKILL)
            if f.kind == "agent_freeze":
                self.frozen.append((time.monotonic() + f.end - f.start, f"agent-{f.vehicles[0]}"))
        for due, n in [x for x in self.frozen if x[0] <= time.monotonic()]:
            self.frozen.remove((due, n))
            if self.procs[n].poll() is None:
                os.kill(self.procs[n].pid, signal.SIGCONT)
        return router_faults

    def _restart_agents(self) -> None:
        """An agent died (crash, kill -9): start it again; it re-initialises from GNSS and
        rejoins. Each restart is reported with the time until its first estimate."""
        for n in [n for n, p in self.procs.items() if n != "emulator" and p.poll() is not None]:
            if sum(r["process"] == n for r in self.restarts) >= self.max_restarts:
                raise RuntimeError(f"{n} exited {self.max_restarts + 1} times; see {self.out / 'logs'}")
            now, rc, vid = time.monotonic(), self.procs[n].returncode, n.removeprefix("agent-")
            log.warning("%s exited with %s; restarting it", n, rc)
            _spawn(self.procs, n, self._agent_args(vid), self._log(n, "a"), self.agent_env)
            self.restarts.append({"process": n, "exit_code": rc, "at_s": now - self.wall0, "_t": now,
                                  "_after_t": self._fleet_t(), "rejoined_after_s": None})

    def _note_rejoins(self) -> None:
        """An agent is back with its first estimate of a sensor time after its restart; the
        emulator with anyone's after its resume point. (Estimates the old process sent before it
        died may still arrive after the restart: they are not a rejoin.)"""
        rec = self.rec
        for r in self.restarts:
            if r["rejoined_after_s"] is not None:
                continue
            v = r["process"].removeprefix("agent-")
            if r["process"] in ("emulator", "router"):
                fresh = [u for u, t in rec.latest_t.items() if t > r["_after_t"]]
            else:
                fresh = [v] if rec.latest_t.get(v, -math.inf) > r["_after_t"] else []
            seen = max((rec.last_wall[u] for u in fresh if u in rec.last_wall), default=-math.inf)
            if seen > r["_t"]:
                r["rejoined_after_s"] = seen - r["_t"]
                log.warning("%s rejoined %.2f s after its restart", r["process"], r["rejoined_after_s"])

    def _report(self) -> None:
        if not self.progress or time.monotonic() - self.last <= 0.5:
            return
        rec = self.rec
        self.last = now_w = time.monotonic()
        if now_w - self.last_table > 2.0:  # rates over two seconds
            self.last_table = now_w
            self.table = status_table(self.vehicles, rec.latest_t, rec.diag, self.prev_diag)
            self.prev_diag = dict(rec.diag)
        if self.play0 is None and rec.recorded:
            self.play0 = now_w
        self.progress(FleetProgress(
            self.title, "playing" if rec.recorded else "starting", self._fleet_t(), self.end_t,
            sum(now_w - w < 3.0 for w in rec.last_wall.values()), len(self.vehicles), rec.recorded,
            now_w - self.wall0, self.table, now_w - self.play0 if self.play0 is not None else 0.0))

    def stop(self) -> None:
        """Stop every child; a second Ctrl-C while they are stopped waits until they are (they
        run in their own sessions: the terminal's signal never reaches them)."""
        with _termination_deferred():
            for p in self.procs.values():  # a frozen process would not see the SIGTERM
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(p.pid, signal.SIGCONT)
            _stop_all(self.procs)
            for t in self.rec_tasks:
                t.cancel()
            self.rec.close()
            for lf in self.logs:
                lf.close()

    def statistics(self) -> dict:
        stats = self.stats
        stats["exit_codes"] = {n: p.returncode for n, p in self.procs.items()}
        stats["restarts"] = [{k: v for k, v in r.items() if not k.startswith("_")} for r in self.restarts]
        # process faults the run never applied: the fleet's clock stopped short of them, or their
        # process was not running (the run then did not test what its schedule says)
        stats["faults_not_applied"] = [{"kind": f.kind, "start_s": f.start, "vehicles": list(f.vehicles)}
                                       for f in [*self.missed, *self.pending]]
        stats["recorded"], stats["codec_errors"] = self.rec.recorded, self.rec.codec_errors
        stats["rejected"] = dict(self.rec.rejected)
        stats["recorded_by_key"] = dict(sorted(self.rec.counts.items()))
        if self.rec.sink_errors:
            stats["recording_sink_errors"] = self.rec.sink_errors
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
                                           env={"RUST_LOG": "zenoh=warn", **os.environ, **(env or {}),
                                                SUPERVISOR_ENV: str(os.getpid())})
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
