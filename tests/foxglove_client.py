"""A minimal Foxglove WebSocket client for the tests (protocol foxglove.sdk.v1): it subscribes
to every channel the server advertises and keeps what it receives."""

from __future__ import annotations

import json
import struct
import threading
import time


class FoxgloveClient(threading.Thread):
    def __init__(self, port: int, seconds: float, until=None) -> None:
        """Listen for at most ``seconds``, or until ``until(client)`` is true."""
        super().__init__(daemon=True)
        self.port, self.seconds, self.until = port, seconds, until
        self.server_info: dict = {}
        self.channels: dict[int, dict] = {}  #: channel id -> its advertisement (topic, schema...)
        self.messages: dict[str, list[tuple[int, bytes]]] = {}  #: topic -> (log time [ns], payload)
        self.subscribed: set[str] = set()  #: topics whose subscription has been sent
        self.error: Exception | None = None

    def run(self) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        deadline = time.monotonic() + self.seconds
        try:
            while True:  # the server may not listen yet
                try:
                    ws = connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=2)
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.2)
            with ws:
                subs: dict[int, str] = {}
                pending: list[tuple[float, dict]] = []  # (advertised at, channel)
                while time.monotonic() < deadline and not (self.until and self.until(self)):
                    # subscribe a little after the advertisement: a subscription that reaches the
                    # server at once can find the channel not yet registered for this client
                    ready = [ch for at, ch in pending if time.monotonic() - at > 0.3]
                    if ready:
                        pending = [(at, ch) for at, ch in pending if ch not in ready]
                        new = []
                        for ch in ready:
                            sid = len(subs) + 1
                            subs[sid] = ch["topic"]
                            new.append({"id": sid, "channelId": ch["id"]})
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                        self.subscribed.update(ch["topic"] for ch in ready)
                    try:
                        m = ws.recv(timeout=0.1)
                    except TimeoutError:
                        continue
                    except ConnectionClosed:  # the server stopped (the run ended)
                        break
                    if isinstance(m, bytes):
                        if m[0] == 1:  # message data: subscription id, log time, payload
                            sid, t = struct.unpack_from("<IQ", m, 1)
                            self.messages.setdefault(subs[sid], []).append((t, m[13:]))
                        continue
                    op = json.loads(m)
                    if op["op"] == "serverInfo":
                        self.server_info = op
                    elif op["op"] == "advertise":
                        for ch in op["channels"]:
                            self.channels[ch["id"]] = ch
                            pending.append((time.monotonic(), ch))
        except Exception as exc:  # noqa: BLE001 - reported to the test
            self.error = exc

    def wait_subscribed(self, topics: set[str], timeout: float = 10.0) -> None:
        """Until the subscriptions to ``topics`` are sent, and a moment for the server to take them."""
        deadline = time.monotonic() + timeout
        while not topics <= self.subscribed and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.2)

    def topics(self) -> dict[str, dict]:
        return {ch["topic"]: ch for ch in self.channels.values()}


def protobuf_doubles(payload: bytes) -> dict[int, list[float]]:
    """The 64-bit fields of a protobuf message, as doubles by field number (packed repeated
    doubles included); other fields are skipped. Enough to read a Foxglove LocationFix."""
    out: dict[int, list[float]] = {}
    i = 0

    def varint() -> int:
        nonlocal i
        shift = v = 0
        while True:
            b = payload[i]
            i += 1
            v |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return v

    while i < len(payload):
        key = varint()
        field, wire = key >> 3, key & 7
        if wire == 0:
            varint()
        elif wire == 1:
            out.setdefault(field, []).append(struct.unpack_from("<d", payload, i)[0])
            i += 8
        elif wire == 2:
            n = varint()
            chunk = payload[i:i + n]
            i += n
            if n and n % 8 == 0 and field == 4:  # the packed covariance
                out.setdefault(field, []).extend(struct.unpack(f"<{n // 8}d", chunk))
        elif wire == 5:
            i += 4
        else:
            raise ValueError(f"protobuf wire type {wire}")
    return out
