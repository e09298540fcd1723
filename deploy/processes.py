"""Process entry points: one agent (``slcp agent``), the emulator service (``slcp emulate``), the
router and the recorder, each an asyncio program over a Zenoh session that shuts down cleanly on
SIGINT/SIGTERM. An agent's configuration file: :mod:`deploy.agent_config_file`.
"""
from __future__ import annotations

import asyncio
import gc
import logging
import os
import signal
from pathlib import Path

from slcp.transport.zenoh_bus import ZenohConfig

from .agent_config_file import (  # noqa: F401 - the configuration's names, where they were
    MAX_LEASE_MS,
    ConfigError,
    load_agent_config,
    security_config,
    zenoh_config,
)

log = logging.getLogger(__name__)

SUPERVISOR_ENV = "SLCP_SUPERVISOR_PID"


def _install_signals(stop: asyncio.Event) -> None:
    """``stop`` is set on SIGINT/SIGTERM, and when the launcher that started this process
    (:data:`SUPERVISOR_ENV`) is gone: a launcher killed with SIGKILL leaves no process behind."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # pragma: no cover - non-main thread / platform
            pass
    supervisor = os.environ.get(SUPERVISOR_ENV, "")
    if supervisor.isdigit():
        _watch_tasks.add(loop.create_task(_stop_when_orphaned(int(supervisor), stop)))


_watch_tasks: set[asyncio.Task] = set()


async def _stop_when_orphaned(supervisor: int, stop: asyncio.Event, period: float = 0.5) -> None:
    while not stop.is_set():
        if os.getppid() != supervisor:
            log.warning("the launcher (pid %d) is gone; stopping", supervisor)
            stop.set()
            return
        await asyncio.sleep(period)


#: the collector's young-generation threshold in the long-running processes (CPython's default
#: 700): the filters allocate many short-lived containers, which reference counting frees
GC_GEN0_THRESHOLD = 10_000


def settle_gc() -> None:
    """Once a long-running process is set up: its objects so far (modules, configuration, the
    scenario's truth) move to the collector's permanent generation, so that full collections no
    longer walk them, and young collections run less often. In 25 agents sharing one process
    over 40 s of the grid, the collector's time went 0.70 → 0.23 s (of 18 s of CPU)."""
    gc.freeze()
    gc.set_threshold(GC_GEN0_THRESHOLD, 10, 10)


async def agent_main(config_path: Path, vehicle: str | None, nice: int = 0, stand_in: bool = False) -> int:
    """One agent until SIGINT/SIGTERM; with ``stand_in`` its engine stops estimating once
    started (:mod:`agent.stand_in`: benchmarks of what the rest of a fleet costs)."""
    from slcp.agent.runtime import Agent
    from slcp.agent.stand_in import StandInEngine
    from slcp.transport.zenoh_bus import ZenohBus

    cfg, zcfg = load_agent_config(config_path, vehicle)
    if nice:  # a lower scheduling priority (launcher: emulated hardware first on a shared machine)
        try:
            os.nice(nice)
        except OSError as exc:
            log.warning("%s: could not lower the priority by %d: %s", cfg.vehicle, nice, exc)
    stop = asyncio.Event()
    _install_signals(stop)
    bus = ZenohBus(zcfg)
    agent = Agent(cfg, bus, StandInEngine) if stand_in else Agent(cfg, bus)
    settle_gc()
    reach = asyncio.create_task(report_reachability(bus, zcfg.connect, cfg.vehicle))
    try:
        await agent.run(stop)
    finally:
        reach.cancel()
        await bus.close()
    # the full account (sequencer, tables, filters, misbehaviour: what its last diagnostics say),
    # not only the engine's own counters: a late or dropped fix shows here
    eng = agent.engine
    last = eng.diagnostics(eng.seq.t).counters if eng.seq.t is not None else dict(eng.counters)
    log.info("%s: stopped; counters %s", cfg.vehicle, last)
    return 0


async def router_main(zcfg: ZenohConfig) -> int:
    """An infrastructure router (Zenoh router mode) until SIGINT/SIGTERM."""
    from slcp.transport.zenoh_bus import ZenohBus

    stop = asyncio.Event()
    _install_signals(stop)
    bus = ZenohBus(zcfg)
    log.info("router listening on %s", ", ".join(zcfg.listen))
    try:
        await stop.wait()
    finally:
        await bus.close()
    return 0


async def report_reachability(bus, endpoints: tuple[str, ...], who: str, first: float = 2.0,
                              every: float = 15.0) -> None:
    """Say, one line at a time, that ``endpoints`` cannot be reached while the session has no link
    (Zenoh keeps trying in the background), and once that it is connected after all."""
    if not endpoints:
        return
    await asyncio.sleep(first)
    warned = False
    while not bus.connected():
        log.warning("%s: cannot reach %s yet; retrying (Ctrl-C to stop)", who, ", ".join(endpoints))
        warned = True
        await asyncio.sleep(every)
    if warned:
        log.warning("%s: connected", who)


async def wait_for_agent(bus, vehicle: str, inputs: list[str], timeout: float) -> bool:
    """Wait up to ``timeout`` [s] for the agent of ``vehicle`` (its liveliness token) and then for
    this bus to know of subscriptions to each of the ``inputs`` keys (a publication before that
    is lost: the first seconds of a log played fast). Whether both came in time; warns if not."""
    from slcp.transport import keys

    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    seen = asyncio.Event()

    def on_alive(key: str, up: bool) -> None:
        if up and key.rsplit("/", 1)[-1] == vehicle:
            seen.set()

    bus.watch_alive(keys.alive("agent", vehicle), on_alive)
    try:
        await asyncio.wait_for(seen.wait(), timeout)
    except TimeoutError:
        log.warning("no agent %s after %.0f s; publishing anyway", vehicle, timeout)
        return False
    if not await bus.wait_subscribed(inputs, max(0.0, end - loop.time())):
        log.warning("agent %s is up but %s not subscribed after %.0f s; publishing anyway",
                    vehicle, ", ".join(inputs), timeout)
        return False
    return True


async def recorder_main(zcfg: ZenohConfig, path: Path | None, bag: Path | None = None,
                        view_port: int | None = None, foxglove_port: int | None = None,
                        scenario: str | None = None, bag_inputs: bool = False) -> int:
    """Record every estimate and diagnostics message to ``path`` (appending; None: no JSON
    lines), with ``bag`` to a ROS 2 bag in MCAP storage (with ``bag_inputs``, the vehicles' inputs
    too), until SIGINT/SIGTERM. With ``view_port``
    show them live on a map in the browser (:mod:`deploy.live_map`; the site of ``scenario`` if
    given), with ``foxglove_port`` serve them to Foxglove (:mod:`deploy.foxglove_view`)."""
    from slcp.transport.zenoh_bus import ZenohBus

    from .mcap_recording import McapSink
    from .recorder import Recorder
    from .viewers import viewer_sinks

    site = None
    if scenario is not None:
        from slcp.hw_emulation.scenario import load_scenario

        site = load_scenario(scenario)
    sinks: list = viewer_sinks(view_port, foxglove_port, site)  # first: a port that is taken stops here
    stop = asyncio.Event()
    _install_signals(stop)
    if bag is not None:
        sinks.append(McapSink(bag, inputs=bag_inputs))
    bus = ZenohBus(zcfg)
    rec = Recorder(path, sinks=sinks)
    tasks = [*rec.start(bus), asyncio.create_task(report_reachability(bus, zcfg.connect, "record"))]
    try:
        await stop.wait()
    finally:
        for t in tasks:
            t.cancel()
        rec.close()
        await bus.close()
    log.info("recorder stopped: %d recorded, %d bad payloads, refused %s", rec.recorded, rec.codec_errors,
             dict(rec.rejected) or "none")
    return 0


async def emulator_main(scenario: str, seed: int, speed: float | None, zcfg: ZenohConfig,
                        wait_for_agents: float = 20.0, faults_path: Path | None = None,
                        start_at: float | None = None) -> int:
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.service import EmulatorService
    from slcp.hw_emulation.truth import build_truth
    from slcp.transport import keys
    from slcp.transport.zenoh_bus import ZenohBus

    scn = load_scenario(scenario)
    truth = build_truth(scn, stop_seed=seed)
    faults = []
    if faults_path is not None:
        from slcp.hw_emulation.faults import load_faults

        faults = load_faults(faults_path, set(truth.vehicles))
    stop = asyncio.Event()
    _install_signals(stop)
    bus = ZenohBus(zcfg)
    try:
        emu = EmulatorService(truth, bus, seed=seed, speed=speed, faults=faults, start_at=start_at)
        emu.prepare()  # subscribed before the agents start publishing
        settle_gc()
        alive: set[str] = set()

        def on_alive(key: str, up: bool) -> None:
            v = key.rsplit("/", 1)[-1]
            if v not in truth.vehicles:  # not an agent of this scenario (counted by the service)
                if not up:
                    emu.forget_agent(v)
                return
            if up:
                if v not in alive:
                    log.info("agent %s alive", v)
                alive.add(v)
                emu.agent_back(v)
            else:
                alive.discard(v)
                emu.forget_agent(v)
                log.warning("agent %s left", v)

        # the scenario's agents only: a stranger's tokens are dropped in Zenoh's thread
        bus.watch_alive(keys.ROOT + "/alive/agent/*", on_alive, names=frozenset(truth.vehicles))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + wait_for_agents
        while not stop.is_set() and not set(truth.vehicles) <= alive and loop.time() < deadline:
            await asyncio.sleep(0.05)
        missing = set(truth.vehicles) - alive
        if missing:
            log.warning("starting without agents %s", sorted(missing))
        await asyncio.sleep(0.3)  # let the agents' subscriptions propagate
        await emu.run(stop)
        log.info("emulator done: published %s, radio %s, faults %s, unknown liveliness tokens gone %d",
                 emu.published, emu.radio_stats, emu.fault_stats, emu.unknown_liveliness)
    finally:
        await bus.close()
    return 0
