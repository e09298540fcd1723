"""Fleet scaling benchmark (``slcp bench --fleet N,...``): N agent processes on this machine.

For each N, a grid scenario (:mod:`hw_emulation.grid`: IMU 100 Hz, GNSS 5 Hz, UWB 10 Hz to the
at most 7 other vehicles of an intersection, beacons 5 Hz) is run by the launcher at speed 1×
(the emulator paces on the wall clock), with signed beacons and one method per agent; the agents
run at ``nice`` 5 (see :func:`deploy.launcher.run_fleet`) and the vehicles' IMU batches are
staggered (:mod:`hw_emulation.grid`). Measured:

* ``realtime_factor``: sensor time advanced by the fleet's median agent (its newest estimate)
  per second of wall time, over the steady part (once every agent publishes); below 1 the
  agents do not keep up; above 1 they were catching up: already behind when every agent
  first published (an overloaded machine starts late), which ``lag_p99_s`` shows;
* ``lag_p99_s``: how far the agents' newest estimates trail the 1x clock at the end (99th
  percentile over agents; sensor time): the clock is read from one vehicle's GNSS fixes at
  the router (the earliest arrival relative to its fix time) — it grows when the fleet falls
  behind;
* ``cpu_pct_per_agent`` (mean, max), ``emulator_cpu_pct`` and ``launcher_cpu_pct`` (the
  launcher: its Zenoh router, the recorder and this monitor): CPU time over the steady part per
  wall time (/proc), 100 % = one core; ``machine_cpu_pct``: all processes of the run, the
  launcher included;
* ``threads_per_agent``: the threads of an agent process (max over agents; Python's and
  Zenoh's);
* ``rss_mb_per_agent`` (mean, max of each agent's peak resident set, /proc ``VmHWM``);
* ``beacon_latency_ms`` p50/p99: from a beacon's publication by its sender to its delivery to
  each receiver by the emulated radio (whose own emulated latency is 0 in this scenario), both
  seen by a tap of the launcher's Zenoh router at arrival;
* ``sensor_dropped``: sensor messages lost in the agents' queues or dropped as too late by
  their sequencers (``queue_dropped_imu|gnss|uwb`` + ``seq_late_dropped``), summed;
* ``windows``: the steady part in consecutive ``WINDOW_S`` windows, each with its machine CPU
  and beacon latency p99 (by publication time), and their worst, ``machine_cpu_pct_peak`` and
  ``beacon_p99_ms_worst_window``: the load is not even over the grid's run (its vehicles
  start near each other, up to 60 ranges an agent a second, and drive apart), and a fleet that
  keeps up on average may saturate the machine in its busiest window.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from slcp.agent.methods import DEFAULT_FUSION
from slcp.hw_emulation.grid import grid_scenario_toml
from slcp.transport import keys
from slcp.transport.codec import decode

from .fleet_capacity import FLEET_ENGINES

log = logging.getLogger(__name__)

_TICK = os.sysconf("SC_CLK_TCK")
#: length of the windows of ``FleetMonitor.result()["windows"]`` [s]
WINDOW_S = 5.0


def _proc_cpu_s(pid: int) -> float | None:
    """User + system CPU time of a process [s] (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _TICK
    except (OSError, IndexError, ValueError):
        return None


def _proc_status(pid: int, field: str) -> int | None:
    """An integer field of /proc/<pid>/status (kB for sizes; None once the process is gone)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def _proc_peak_rss_mb(pid: int) -> float | None:
    """Peak resident set size (VmHWM) [MB]."""
    kb = _proc_status(pid, "VmHWM")
    return None if kb is None else kb / 1024.0


@dataclasses.dataclass
class FleetMonitor:
    """Samples a running fleet (see :func:`deploy.launcher.run_fleet`'s ``monitor``)."""

    vehicles: list[str]

    def __post_init__(self) -> None:
        self.procs: dict = {}
        self._lock = threading.Lock()
        self._tx: dict[int, float] = {}  # hash of a beacon payload -> arrival time (monotonic)
        self._rx: list[tuple[float, int]] = []
        self.latencies: list[float] = []
        self.latency_t: list[float] = []  # publication times (monotonic) of ``latencies``
        self.points: list[tuple[float, dict]] = []  # (wall, CPU per process) of the steady part
        self.unmatched = 0
        self.steady: tuple[float, dict, float] | None = None  # (wall, cpu per process, median t)
        self.last: tuple[float, dict, float] | None = None
        #: wall time (monotonic) of sensor time 0 on the emulator's 1x clock: the least
        #: (arrival − fix time) over one vehicle's GNSS fixes seen at the router
        self.emulator_t0: float | None = None
        self.lag_end: list[float] = []
        self.rss: dict[str, float] = {}
        self.threads: dict[str, int] = {}
        self._next = 0.0

    def attach(self, bus, procs: dict, endpoint: str = "") -> None:  # noqa: ARG002 - the monitor interface
        self.procs = procs
        bus.tap(f"{keys.ROOT}/radio/tx/*", self._on_tx)
        bus.tap(f"{keys.ROOT}/radio/rx/*", self._on_rx)
        if self.vehicles:
            bus.tap(keys.gnss(self.vehicles[0]), self._on_clock)

    def _on_clock(self, key: str, payload: bytes) -> None:  # Zenoh thread
        now = time.monotonic()
        try:
            t = float(decode(payload).t)
        except Exception:  # noqa: BLE001 - not a fix: no clock reading
            return
        with self._lock:
            if self.emulator_t0 is None or now - t < self.emulator_t0:
                self.emulator_t0 = now - t

    def _on_tx(self, key: str, payload: bytes) -> None:  # Zenoh thread
        now = time.monotonic()
        with self._lock:
            self._tx[hash(payload)] = now

    def _on_rx(self, key: str, payload: bytes) -> None:  # Zenoh thread
        now = time.monotonic()
        with self._lock:
            self._rx.append((now, hash(payload)))

    def _match(self) -> None:
        with self._lock:
            rx, self._rx = self._rx, []
            for t_rx, h in rx:
                t_tx = self._tx.get(h)
                if t_tx is None:
                    self.unmatched += 1
                else:
                    self.latencies.append(t_rx - t_tx)
                    self.latency_t.append(t_tx)
            cutoff = time.monotonic() - 10.0
            if len(self._tx) > 200_000:
                self._tx = {h: t for h, t in self._tx.items() if t > cutoff}

    def _cpu(self) -> dict[str, float]:
        cpu = {n: c for n, p in self.procs.items() if (c := _proc_cpu_s(p.pid)) is not None}
        if (c := _proc_cpu_s(os.getpid())) is not None:
            cpu["launcher"] = c
        return cpu

    def sample(self, rec) -> None:
        """Called by the launcher every 0.2 s with its recorder."""
        self.rec = rec
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + 1.0
        self._match()
        for n, p in self.procs.items():
            r = _proc_peak_rss_mb(p.pid)
            if r is not None:
                self.rss[n] = max(self.rss.get(n, 0.0), r)
            k = _proc_status(p.pid, "Threads")
            if k is not None:
                self.threads[n] = max(self.threads.get(n, 0), k)
        ts = [rec.latest_t[v] for v in self.vehicles if v in rec.latest_t]
        if len(ts) < len(self.vehicles):
            return  # not every agent publishes yet
        point = (now, self._cpu(), float(np.median(ts)))
        if self.steady is None:
            self.steady = point
        self.last = point
        self.points.append(point[:2])
        # without a fix seen, the clock as if the median agent was on time when all published
        t0 = self.emulator_t0 if self.emulator_t0 is not None else self.steady[0] - self.steady[2]
        self.lag_end = [(now - t0) - t for t in ts]

    def _windows(self, lat_ms: np.ndarray) -> dict:
        """Machine CPU [%] and beacon latency p99 [ms] per ``WINDOW_S`` of the steady part."""
        rows = []
        t_pub = np.array(self.latency_t)
        k = 0
        pts = self.points
        while k + 1 < len(pts):
            j = k + 1  # the window runs from sample k to the first sample WINDOW_S later
            while j + 1 < len(pts) and pts[j][0] - pts[k][0] < WINDOW_S - 1e-6:
                j += 1
            (w0, c0), (w1, c1) = pts[k], pts[j]
            if w1 - w0 < 0.5 * WINDOW_S:
                break  # a short tail
            cpu = 100.0 * sum(c1[n] - c0[n] for n in c1 if n in c0) / (w1 - w0)
            sel = lat_ms[(t_pub >= w0) & (t_pub < w1)]
            rows.append({"t_s": w0 - pts[0][0], "wall_s": w1 - w0, "machine_cpu_pct": cpu,
                         "beacon_p99_ms": float(np.percentile(sel, 99)) if len(sel) else None, "n": int(len(sel))})
            k = j
        p99 = [r["beacon_p99_ms"] for r in rows if r["beacon_p99_ms"] is not None]
        return {"windows": rows,
                "machine_cpu_pct_peak": max((r["machine_cpu_pct"] for r in rows), default=None),
                "beacon_p99_ms_worst_window": max(p99, default=None)}

    def result(self) -> dict:
        self._match()
        rec = getattr(self, "rec", None)
        out: dict = {"agents": len(self.vehicles)}
        if rec is None or self.steady is None or self.last is None or self.last[0] - self.steady[0] < 2.0:
            out["error"] = "the fleet never ran with every agent publishing for 2 s"
            return out
        (w0, c0, t0), (w1, c1, t1) = self.steady, self.last
        wall = w1 - w0
        pct = {n: 100.0 * (c1[n] - c0[n]) / wall for n in c1 if n in c0}
        agent_pct = [v for n, v in pct.items() if n.startswith("agent-")]
        agent_rss = [v for n, v in self.rss.items() if n.startswith("agent-")]
        lat = np.array(self.latencies) * 1e3
        dropped: dict[str, int] = {}
        for v in self.vehicles:
            _, c, _ = rec.diag.get(v, (None, {}, {}))
            for k in ("queue_dropped_imu", "queue_dropped_gnss", "queue_dropped_uwb", "queue_dropped_beacon",
                      "seq_late_dropped"):
                dropped[k] = dropped.get(k, 0) + int(c.get(k, 0))
        out.update(
            {
                "steady_wall_s": wall,
                "realtime_factor": (t1 - t0) / wall,
                "lag_p99_s": float(np.percentile(self.lag_end, 99)) if self.lag_end else None,
                "cpu_pct_per_agent": {"mean": float(np.mean(agent_pct)), "max": float(np.max(agent_pct))}
                if agent_pct
                else None,
                "emulator_cpu_pct": pct.get("emulator"),
                "launcher_cpu_pct": pct.get("launcher"),
                "machine_cpu_pct": float(sum(pct.values())),
                "rss_mb_per_agent": {"mean": float(np.mean(agent_rss)), "max": float(np.max(agent_rss))}
                if agent_rss
                else None,
                "emulator_rss_mb": self.rss.get("emulator"),
                "threads_per_agent": max((k for n, k in self.threads.items() if n.startswith("agent-")), default=None),
                "beacon_latency_ms": (
                    {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)), "n": int(len(lat))}
                    if len(lat)
                    else None
                ),
                "beacons_unmatched": self.unmatched,
                **self._windows(lat),
                "sensor_dropped": int(sum(v for k, v in dropped.items() if k != "queue_dropped_beacon")),
                "dropped_by_kind": dropped,
            }
        )
        return out


class MapWatcher(threading.Thread):
    """A client of the live map (:mod:`deploy.live_map`) on 127.0.0.1:``port`` that takes every
    frame until :meth:`stop`, as an open page does; it waits for the server to come up."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True, name="map-watcher")
        self.port, self.frames, self.vehicles = port, 0, 0
        self._stop_event = threading.Event()
        self.start()

    def run(self) -> None:
        import json

        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        while not self._stop_event.is_set():
            try:
                with connect(f"ws://127.0.0.1:{self.port}/ws", open_timeout=2) as ws:
                    while not self._stop_event.is_set():
                        try:
                            m = json.loads(ws.recv(timeout=0.5))
                        except TimeoutError:
                            continue
                        if m.get("type") == "state":
                            self.frames += 1
                            self.vehicles = max(self.vehicles, len({e["vehicle"] for e in m["estimates"]}))
            except (OSError, ConnectionClosed, TimeoutError):
                self._stop_event.wait(0.2)

    def stop(self) -> tuple[int, int]:
        self._stop_event.set()
        self.join(5)
        return self.frames, self.vehicles


def run_fleet_point(n: int, duration: float = 40.0, method: str = "SL-CP", sign: bool = True,
                    out: Path | None = None, agent_nice: int = 5, zenoh_mode: str = "client",
                    imu_batch: int = 20, fusion: str = DEFAULT_FUSION, view: bool = False,
                    engine: str = "full") -> dict:
    """One benchmark point: ``n`` agents on the grid at 1× with ``imu_batch`` IMU samples per
    message (20: 5 messages a second at 100 Hz), CP methods fusing by ``fusion``; returns
    :meth:`FleetMonitor.result`. A client-mode fleet is secured as ``slcp run``'s is (mutual
    TLS, the access control list); a peer-mode one cannot be, and runs on plain TCP. With
    ``view`` the live map is served and watched the whole run by a client that takes every
    frame, as an open page does (``view_frames``: the frames it took; ``view_vehicles``: the
    most vehicles one frame showed). With ``engine`` ``"stand-in"`` the agents stop estimating
    once started (:mod:`agent.stand_in`): the point measures the fleet without its estimation."""
    from .launcher import free_port, run_fleet

    if engine not in FLEET_ENGINES:
        raise ValueError(f"engine must be one of {', '.join(FLEET_ENGINES)}, got {engine!r}")

    with tempfile.TemporaryDirectory(prefix=f"slcp-bench-{n}-") as tmp:
        base = Path(out) if out is not None else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        scn = base / f"grid-{n}.toml"
        scn.write_text(grid_scenario_toml(n, duration, imu_batch=imu_batch))
        mon = FleetMonitor([f"G{i}" for i in range(n)])
        port = free_port() if view else None
        watcher = MapWatcher(port) if port is not None else None
        wall0 = time.monotonic()
        stats = run_fleet(str(scn), methods=(method,), speed=1.0, seed=0, out=base / "run", sign=sign,
                          monitor=mon, evaluate=False, wait_agents=max(30.0, 1.5 * n), agent_nice=agent_nice,
                          zenoh_mode=zenoh_mode, fusion=fusion, secure=zenoh_mode == "client", view_port=port,
                          agent_args=("--stand-in",) if engine == "stand-in" else ())
        res = mon.result()
        if watcher is not None:
            res["view_frames"], res["view_vehicles"] = watcher.stop()
        res["method"] = method
        res["engine"] = engine
        res["fusion"] = fusion
        res["agent_nice"] = agent_nice
        res["zenoh_mode"] = zenoh_mode
        res["secure"] = zenoh_mode == "client"
        res["imu_batch"] = imu_batch
        res["duration_s"] = duration
        res["total_wall_s"] = time.monotonic() - wall0
        res["restarts"] = len(stats["processes"].get("restarts", []))
        return res
