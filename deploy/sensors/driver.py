"""``slcp sensors``: a vehicle computer's sensor driver, from serial ports or files to the bus.

Sources are given as ``FORMAT:PATH[@BAUD]``:

* ``--gnss nmea:/dev/ttyACM0@115200`` NMEA 0183 (:mod:`deploy.sensors.nmea`);
* ``--gnss ubx:/dev/ttyACM0`` u-blox UBX NAV-PVT (:mod:`deploy.sensors.ubx`);
* ``--imu csv:/dev/ttyUSB0@921600`` IMU text lines (:mod:`deploy.sensors.imu`).

A character device is opened as a serial port with pyserial (8N1, ``BAUD`` default 115200) and
its messages are published as they arrive. A regular file is a log: it is read to the end and
its messages are paced on the wall clock by their own time stamps at ``speed`` × real time (one
clock for all sources, started by the first message of any), the log files' messages merged in
time order (:class:`_TimeMerge`), once the vehicle's agent is up and subscribed to them (up to
``wait_agent`` s: what is published before that is lost). Each message is published on the
vehicle's sensor topics; every second a :class:`Diagnostics` message on
``slcp/v1/diag/<vehicle>.sensors`` carries the parsers' counters (bad sentences, frames, samples,
gaps). Bad input is counted and skipped; a serial port that fails is reopened every second.

Reading is done in one thread per source (blocking reads) that hands chunks to the event loop
through a bounded queue, so a fast file never floods memory.
"""

from __future__ import annotations

import asyncio
import logging
import stat
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from slcp.transport import keys
from slcp.transport.codec import encode
from slcp.transport.messages import Diagnostics, GnssFix, ImuBatch

from .imu import ImuAdapter, ImuFormatError, parse_imu_line
from .nmea import NmeaFixAssembler
from .ubx import UbxFixReader

log = logging.getLogger(__name__)

FORMATS = {"gnss": ("nmea", "ubx"), "imu": ("csv",)}


class SourceError(ValueError):
    """A source specification or device cannot be used."""


@dataclass(frozen=True)
class SourceSpec:
    """``FORMAT:PATH[@BAUD]`` parsed; ``serial`` tells a device from a log file."""

    kind: str  #: "gnss" or "imu"
    fmt: str
    path: Path
    baud: int = 115200
    serial: bool = False

    @classmethod
    def parse(cls, kind: str, text: str) -> SourceSpec:
        fmt, sep, rest = text.partition(":")
        if not sep or fmt not in FORMATS[kind] or not rest:
            raise SourceError(f"--{kind} {text!r}: expected FORMAT:PATH[@BAUD] with FORMAT one of "
                              f"{', '.join(FORMATS[kind])}")
        path, at, baud = rest.rpartition("@") if "@" in rest else (rest, "", "")
        b = 115200
        if at:
            try:
                b = int(baud)
            except ValueError:
                raise SourceError(f"--{kind} {text!r}: baud rate {baud!r} is not an integer") from None
            if b <= 0:
                raise SourceError(f"--{kind} {text!r}: baud rate must be positive")
        p = Path(path)
        try:
            st = p.stat()
        except OSError as exc:
            raise SourceError(f"--{kind} {text!r}: {path}: {exc.strerror}") from None
        if stat.S_ISCHR(st.st_mode):
            return cls(kind, fmt, p, b, True)
        if not stat.S_ISREG(st.st_mode):
            raise SourceError(f"--{kind} {text!r}: {path} is neither a character device nor a file")
        return cls(kind, fmt, p, b, False)


class _Reader(threading.Thread):
    """Blocking reads of one source, handed to the loop as ``(host time, bytes)`` (``b""`` at EOF)."""

    def __init__(self, spec: SourceSpec, queue: asyncio.Queue, loop: asyncio.AbstractEventLoop,
                 stop: threading.Event, counters: dict[str, int]) -> None:
        super().__init__(daemon=True, name=f"read-{spec.kind}")
        self.spec, self.queue, self.loop, self.stop, self.counters = spec, queue, loop, stop, counters

    def _put(self, item) -> bool:
        fut = asyncio.run_coroutine_threadsafe(self.queue.put(item), self.loop)
        while not self.stop.is_set():
            try:
                fut.result(timeout=0.2)
                return True
            except TimeoutError:
                continue
        fut.cancel()
        return False

    def run(self) -> None:
        try:
            if self.spec.serial:
                self._serial()
            else:
                with open(self.spec.path, "rb") as fh:
                    while not self.stop.is_set():
                        chunk = fh.read(65536)
                        if not self._put((time.time(), chunk)) or not chunk:
                            return
        except Exception:  # noqa: BLE001 - a reader must report, never die silently
            log.exception("%s reader failed", self.spec.kind)
            self._put((time.time(), b""))

    def _serial(self) -> None:
        import serial  # pyserial

        while not self.stop.is_set():
            try:
                with serial.Serial(str(self.spec.path), self.spec.baud, timeout=0.1) as port:
                    while not self.stop.is_set():
                        chunk = port.read(max(1, port.in_waiting))
                        if chunk and not self._put((time.time(), chunk)):
                            return
            except (OSError, serial.SerialException) as exc:
                self.counters[f"{self.spec.kind}_port_errors"] = (
                    self.counters.get(f"{self.spec.kind}_port_errors", 0) + 1
                )
                log.warning("%s: %s; reopening in 1 s", self.spec.path, exc)
                self.stop.wait(1.0)


def _message_time(m: GnssFix | ImuBatch) -> float:
    return float(m.t if isinstance(m, GnssFix) else m.t[-1])


class _TimeMerge:
    """The messages of several log files, handed on in time order across the files. Each
    file's parser feeds a bounded queue of its own; a message goes out once every file still
    being read has one waiting, the earliest first. Paced as two independent streams, the
    files would reach the agent in whatever order the driver's tasks get the CPU: on a busy
    machine at 8x a fix can come later than the IMU by more than the agent's hold (0.25 s of
    sensor time, 31 ms of wall time), and the agent drops it as late."""

    def __init__(self, kinds: list[str]) -> None:
        self.queues: dict[str, asyncio.Queue] = {k: asyncio.Queue(256) for k in kinds}

    async def put(self, kind: str, msgs) -> None:
        for m in msgs:
            await self.queues[kind].put(m)

    async def end(self, kind: str) -> None:
        await self.queues[kind].put(None)

    async def run(self, send) -> None:
        """``await send(m)`` for every message, in time order, until every file has ended."""
        heads: dict[str, GnssFix | ImuBatch] = {}
        reading = list(self.queues)
        while True:
            for kind in [k for k in reading if k not in heads]:
                m = await self.queues[kind].get()
                if m is None:
                    reading.remove(kind)
                else:
                    heads[kind] = m
            if not heads:
                return
            first = min(heads, key=lambda k: _message_time(heads[k]))
            await send(heads.pop(first))


class Pacer:
    """Wall-clock pacing of log files by message time at ``speed`` × real time."""

    def __init__(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.speed = speed
        self._origin: tuple[float, float] | None = None  # (message time, loop time)

    async def wait(self, t: float) -> None:
        loop = asyncio.get_running_loop()
        if self._origin is None:
            self._origin = (t, loop.time())
        due = self._origin[1] + (t - self._origin[0]) / self.speed
        delay = due - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)


class SensorDriver:
    """Parses the sources and publishes their messages (see the module docstring)."""

    def __init__(self, bus, vehicle: str, gnss: SourceSpec | None = None, imu: SourceSpec | None = None,
                 adapter: ImuAdapter | None = None, accel_unit: float = 1.0, gyro_unit: float = 1.0,
                 uere: float = 2.5, speed: float = 1.0) -> None:
        keys.check_name(vehicle)
        if gnss is None and imu is None:
            raise SourceError("nothing to read: give --gnss and/or --imu")
        self.bus, self.vehicle = bus, vehicle
        self.gnss, self.imu = gnss, imu
        self.adapter = adapter or ImuAdapter(vehicle)
        self.units = (accel_unit, gyro_unit)
        self.nmea = NmeaFixAssembler(vehicle, uere=uere)
        self.ubx = UbxFixReader(vehicle)
        self.pacer = Pacer(speed)
        self._merge = _TimeMerge([s.kind for s in (gnss, imu) if s is not None and not s.serial])
        self.counters: dict[str, int] = {"published_imu": 0, "published_gnss": 0, "imu_bad_line": 0}

    def all_counters(self) -> dict[str, int]:
        c = dict(self.counters)
        if self.gnss is not None:
            c.update(self.nmea.counters if self.gnss.fmt == "nmea" else self.ubx.counters)
        if self.imu is not None:
            c.update(self.adapter.counters)
        return c

    async def run(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        halt = threading.Event()
        tasks = []
        for spec, handler in ((self.gnss, self._gnss_chunk), (self.imu, self._imu_chunk)):
            if spec is None:
                continue
            q: asyncio.Queue = asyncio.Queue(64)
            _Reader(spec, q, loop, halt, self.counters).start()
            tasks.append(asyncio.ensure_future(self._consume(spec, q, handler)))
        if self._merge.queues:
            tasks.append(asyncio.ensure_future(self._merge.run(self._paced_send)))
        diag = asyncio.ensure_future(self._diagnostics(stop))
        done = asyncio.ensure_future(asyncio.gather(*tasks))
        stopper = asyncio.ensure_future(stop.wait())
        try:
            await asyncio.wait({done, stopper}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            halt.set()
            for t in (*tasks, stopper, diag):
                t.cancel()
            await asyncio.gather(*tasks, stopper, diag, return_exceptions=True)
            await self._publish_diag()
        log.info("%s sensors done: %s", self.vehicle, self.all_counters())

    async def _consume(self, spec: SourceSpec, q: asyncio.Queue, handler) -> None:
        carry = b""
        while True:
            host_t, chunk = await q.get()
            if not chunk:  # end of a log file
                msgs = handler(carry + b"\n", host_t) if carry else []
                if spec.kind == "gnss" and spec.fmt == "nmea":
                    msgs += self.nmea.flush()
                if spec.kind == "imu":
                    last = self.adapter.flush()
                    msgs += [last] if last is not None else []
                await self._publish(msgs, spec)
                if not spec.serial:
                    await self._merge.end(spec.kind)
                return
            if spec.kind == "gnss" and spec.fmt == "ubx":
                await self._publish(self.ubx.feed(chunk), spec)
                continue
            data = carry + chunk
            cut = data.rfind(b"\n")
            if cut < 0:
                carry = data[-4096:]  # a line never gets longer than this
                continue
            carry = data[cut + 1:]
            await self._publish(handler(data[:cut + 1], host_t), spec)

    def _gnss_chunk(self, data: bytes, host_t: float) -> list[GnssFix]:
        out: list[GnssFix] = []
        for line in data.splitlines():
            out.extend(self.nmea.feed(line))
        return out

    def _imu_chunk(self, data: bytes, host_t: float) -> list[ImuBatch]:
        out: list[ImuBatch] = []
        for raw in data.splitlines():
            try:
                s = parse_imu_line(raw.decode("ascii", errors="replace"), *self.units, host_time=host_t)
            except ImuFormatError:
                self.counters["imu_bad_line"] += 1
                continue
            if s is not None:
                out.extend(self.adapter.push(*s))
        return out

    async def _publish(self, msgs, spec: SourceSpec) -> None:
        """A serial device's messages go out at once; a log file's through the time merge."""
        if not spec.serial:
            await self._merge.put(spec.kind, msgs)
            return
        for m in msgs:
            await self._send(m)

    async def _paced_send(self, m: GnssFix | ImuBatch) -> None:
        await self.pacer.wait(_message_time(m))
        await self._send(m)

    async def _send(self, m: GnssFix | ImuBatch) -> None:
        if isinstance(m, GnssFix):
            await self.bus.publish(keys.gnss(self.vehicle), encode(m))
            self.counters["published_gnss"] += 1
        else:
            await self.bus.publish(keys.imu(self.vehicle), encode(m))
            self.counters["published_imu"] += 1

    async def _publish_diag(self) -> None:
        d = Diagnostics(f"{self.vehicle}.sensors", time.time(), self.all_counters())
        await self.bus.publish(keys.diag(d.source), encode(d))

    async def _diagnostics(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            await asyncio.sleep(1.0)
            await self._publish_diag()


async def sensors_main(zcfg, vehicle: str, gnss: SourceSpec | None, imu: SourceSpec | None,
                       adapter: ImuAdapter, units: tuple[float, float], uere: float, speed: float,
                       wait_agent: float = 30.0) -> dict:
    """Run a :class:`SensorDriver` over Zenoh until its log files end or SIGINT/SIGTERM. Log files
    start once the agent of ``vehicle`` listens to them (at most ``wait_agent`` s; 0: at once);
    serial devices publish what they read from the start."""
    from slcp.transport.zenoh_bus import ZenohBus

    from ..processes import _install_signals, report_reachability, wait_for_agent

    stop = asyncio.Event()
    _install_signals(stop)
    bus = ZenohBus(zcfg)
    reach = asyncio.create_task(report_reachability(bus, zcfg.connect, f"sensors {vehicle}"))
    try:
        bus.declare_alive(keys.alive("sensors", vehicle))
        drv = SensorDriver(bus, vehicle, gnss, imu, adapter, *units, uere=uere, speed=speed)
        logs = [s for s in (gnss, imu) if s is not None and not s.serial]
        if logs and wait_agent > 0:
            topics = [keys.gnss(vehicle) if s.kind == "gnss" else keys.imu(vehicle) for s in logs]
            waiting = asyncio.ensure_future(wait_for_agent(bus, vehicle, topics, wait_agent))
            stopper = asyncio.ensure_future(stop.wait())
            await asyncio.wait({waiting, stopper}, return_when=asyncio.FIRST_COMPLETED)
            for t in (waiting, stopper):
                t.cancel()
        await drv.run(stop)
        return drv.all_counters()
    finally:
        reach.cancel()
        await bus.close()

