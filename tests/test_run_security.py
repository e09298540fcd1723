"""``slcp run`` is locked down by default: its router admits only the run's own certificates
(mutual TLS) and lets each process publish only under its own keys, and the recorder takes a
message only on the key of the sender it names, in the scenario's time window. Each forgery that
once changed a run's results is tried here while a real fleet runs."""

from __future__ import annotations

import asyncio
import json
import re
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest

from slcp.deploy.launcher import run_fleet
from slcp.deploy.zenoh_security import client_config
from slcp.transport import keys
from slcp.transport.codec import encode
from slcp.transport.messages import Diagnostics, Estimate
from slcp.transport.security import create_fleet
from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

from conftest import short_scenario

pytestmark = pytest.mark.fleet

FORGED_LAT = 0.1  # [rad] far from every shipped scenario: a forged estimate is easy to spot
N = 20  # forgeries of each kind


def _estimate(vehicle: str, method: str, t: float) -> bytes:
    return encode(Estimate(vehicle, method, t, np.array([FORGED_LAT, 2.0, 50.0]), np.zeros(3), np.zeros(3),
                           np.eye(3), first_stopped=True))


class _Forger:
    """A monitor of :func:`run_fleet` that, once the fleet's processes are up, tries the forgeries
    from a thread of its own (a Zenoh session opening must not hold up the launcher's loop)."""

    def __init__(self, out: Path, stranger_dir: Path) -> None:
        self.out, self.stranger_dir = out, stranger_dir
        self.outcome: dict[str, object] = {}
        self.thread: threading.Thread | None = None

    def attach(self, bus, procs, endpoint="") -> None:  # noqa: ARG002 - the monitor interface
        self.thread = threading.Thread(target=lambda: asyncio.run(self._forge()), daemon=True)
        self.thread.start()

    def sample(self, rec) -> None:  # noqa: ARG002 - the monitor interface
        pass

    async def _open(self, cfg: ZenohConfig) -> ZenohBus | str:
        try:
            return ZenohBus(cfg)
        except ConnectionError as exc:
            return str(exc)

    async def _forge(self) -> None:
        conf = tomllib.loads((self.out / "config" / "agent-V0.toml").read_text())
        ep = conf["zenoh"]["connect"][0]
        assert ep.startswith("tls/127.0.0.1:")
        port = ep.rsplit(":", 1)[1]
        # 1. a process of the host without credentials: plain TCP, then TLS with a CA of its own
        for name, cfg in (("plain", ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",))),
                          ("stranger", client_config(self.stranger_dir, "V1", (ep,)))):
            bus = await self._open(cfg)
            self.outcome[name] = bus if isinstance(bus, str) else "connected"
            if not isinstance(bus, str):  # it must not, but then show what it could do
                for k in range(N):
                    await bus.publish(keys.estimate("V2", "SL-CP"), _estimate("V2", "SL-CP", 1.0 + 0.1 * k))
                await bus.close()
        # 2. an insider: V1's own credentials, speaking for V2 (refused by the router's ACL), naming
        # V2 under its own key and stamping a time far outside the scenario (refused and counted
        # by the recorder)
        v1 = await self._open(client_config(self.out / "keys", "V1", (ep,)))
        assert not isinstance(v1, str), v1
        self.outcome["insider"] = "connected"
        try:
            for k in range(N):
                t = 1.0 + 0.1 * k
                await v1.publish(keys.estimate("V2", "SL-CP"), _estimate("V2", "SL-CP", t))
                await v1.publish(keys.diag("V2"), encode(Diagnostics("V2", t, {"beacons_rx": 10**9})))
                await v1.publish(keys.estimate("V1", "SL-CP"), _estimate("V2", "SL-CP", t))
                await v1.publish(keys.estimate("V1", "SP"), _estimate("V1", "SP", 1e6 + k))
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.0)
        finally:
            await v1.close()


@pytest.mark.timeout(300)
def test_a_run_admits_only_its_own_keys_and_refuses_and_counts_forgeries(tmp_path) -> None:
    scn = short_scenario(tmp_path, "paper-1", 10.0)
    out = tmp_path / "run"
    create_fleet(tmp_path / "stranger", ["V1"])  # a valid fleet, but not this run's
    forger = _Forger(out, tmp_path / "stranger")
    m = run_fleet(str(scn), methods=("SP", "SL-CP"), seed=3, out=out, monitor=forger, wait_agents=20.0)
    assert forger.thread is not None
    forger.thread.join(timeout=60)
    assert not forger.thread.is_alive()
    # without the run's certificates there is no session at all
    assert forger.outcome["plain"] != "connected" and forger.outcome["stranger"] != "connected", forger.outcome
    assert forger.outcome["insider"] == "connected"
    # the insider's messages under V1's key: counted and dropped by the recorder, one by one
    assert m["processes"]["rejected"] == {"wrong_key": N, "out_of_window": N}, m["processes"]
    # nothing forged reached the recording: not under V2's key (the router's ACL), not V2's
    # counters, no estimate beyond the scenario's end
    recorded = [json.loads(line) for line in (out / "recorded" / "messages.jsonl").read_text().splitlines()]
    assert recorded
    est = [r for r in recorded if r["type"] == "Estimate"]
    assert {r["vehicle"] for r in est} == {"V0", "V1", "V2"}
    assert not [r for r in est if abs(r["llh"][0] - FORGED_LAT) < 1e-3]
    assert max(r["t"] for r in est) <= 10.0 + 1e-9
    assert not [r for r in recorded if r["type"] == "Diagnostics" and r["counters"].get("beacons_rx") == 10**9]
    # the fleet's clock was never moved by the forged time: no fault, no resume, no restart
    assert m["processes"]["restarts"] == [] and set(m["processes"]["exit_codes"].values()) == {0}
    # and the run is the same as ever: every process on the run's own CA, no plain listener
    assert re.match(r"tls/127\.0\.0\.1:\d+$", tomllib.loads((out / "config" / "agent-V2.toml").read_text())
                    ["zenoh"]["connect"][0])


def test_peer_mode_cannot_be_secured(tmp_path, capsys) -> None:
    with pytest.raises(ValueError, match="insecure"):
        run_fleet("paper-1", out=tmp_path / "peer", zenoh_mode="peer")
    from slcp.deploy.cli import main

    # the command line refuses it before it writes anything
    assert main(["run", "paper-1", "--zenoh-mode", "peer", "--out", str(tmp_path / "cli")]) == 2
    out = capsys.readouterr()
    assert "--zenoh-mode peer" in out.err and "needs --insecure" in out.err and "writing" not in out.out
    assert not (tmp_path / "cli").exists()
