"""A hostile station on an open bus: what a stranger can send to a fleet (pure; SI units).

It floods the fleet with beacons that the agents' cheap checks must shed before any signature
is verified, and churns thousands of liveliness identities. :mod:`deploy.soak` runs it as its
own process against a live fleet and checks that the fleet's state stays bounded and that
every genuine beacon still gets through.

==================  =========================================================================
kind                what the receiving agent must do with it (its counter)
==================  =========================================================================
``stranger``        a fresh beacon from one of the churning identities, with a random key id
                    (``beacon_unknown_key``)
``spoofed_key``     a fresh beacon in a fleet vehicle's name, with a random key id
                    (``beacon_unknown_key``)
``wrong_vehicle``   a fresh beacon in a fleet vehicle's name under another vehicle's (public)
                    key id (``beacon_wrong_vehicle``)
``unsigned``        a fresh beacon in a fleet vehicle's name without a signature
                    (``beacon_unsigned``)
``future``          a beacon in a fleet vehicle's name and key id, dated a day ahead
                    (``beacon_future``); also sent to the radio
``stale``           the same, dated a minute back (``beacon_stale``)
``replay``          a genuine beacon captured from the bus and sent again to its receiver
                    (``<method>_duplicate_or_old``)
``garbage``         random bytes (``codec_errors``)
==================  =========================================================================

A forgery with a fleet vehicle's own key id and a bad signature would need a verification
to refuse: the agents grant a vehicle's name a budget of twice its beacon rate, so such a
flood costs a bounded number of verifications but competes with that vehicle's genuine
beacons. It is left out here (a flood that needs no key), see ``docs/security.md``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slcp.transport import keys
from slcp.transport.codec import encode
from slcp.transport.messages import Beacon
from slcp.transport.security import AUTH_LEN, KEY_ID_LEN

KINDS = ("stranger", "spoofed_key", "wrong_vehicle", "unsigned", "future", "stale", "replay", "garbage")


@dataclass
class HostileStation:
    """The flood of one hostile station.

    Attributes
    ----------
    fleet : list of str
        The fleet's vehicles (the victims, and the names it speaks in).
    key_ids : dict
        Fleet vehicle -> its public key id (in its certificate), for ``wrong_vehicle``.
    methods : tuple of str
        The methods whose beacons it forges.
    identities : int
        Size of the pool of stranger identities (``H0``, ``H1``, ...) that churn through liveliness.
    token_life : float
        [s] how long a stranger's liveliness token lives; ``identities / 2 / token_life`` tokens
        are declared (and as many withdrawn) per second, so half the pool is alive at a time.
    big_size : int
        [bytes] size of the oversized payloads.
    seed : int
    """

    fleet: list[str]
    key_ids: dict[str, bytes]
    methods: tuple[str, ...] = ("SP", "SL-SP", "CP", "SL-CP")
    identities: int = 5000
    token_life: float = 5.0
    big_size: int = 10 << 20
    seed: int = 0
    sent: dict[str, int] = field(default_factory=lambda: dict.fromkeys(KINDS, 0))

    def __post_init__(self) -> None:
        if not self.fleet:
            raise ValueError("a hostile station needs the fleet's vehicle names")
        if self.identities < 2 or self.token_life <= 0:
            raise ValueError("need at least 2 identities and a positive token life")
        self.rng = np.random.default_rng(self.seed)
        self._big_rounds = 0  # oversized payloads sent: the next victim in turn
        #: genuine beacons heard on the bus: (the key they were delivered on, payload)
        self.captured: deque[tuple[str, bytes]] = deque(maxlen=256)
        self.now = 0.0  #: the fleet's sensor time [s], as the newest genuine beacon says
        self.llh = np.array([0.0, 0.0, 0.0])  #: a plausible position (the newest genuine beacon's)
        self._seq = 0
        self._next_token = 0
        self.alive: deque[str] = deque()  #: the stranger identities alive now, oldest first
        self.big = bytes(self.big_size)  # one buffer, sent again and again
        self._pool: list[tuple[str, bytes]] = []
        self._pool_kind = np.zeros(0, int)
        self._pool_t = -np.inf
        self._forged: set[bytes] = set()

    # ----------------------------------------------------------------- what it hears
    def hear(self, key: str, payload: bytes, beacon: Beacon) -> None:
        """A genuine beacon delivered on ``key``: its time is the fleet's clock, and it can be
        replayed (to the same receiver, which has it already). The station's own forgeries,
        heard back, are not taken."""
        if payload in self._forged:
            return
        if beacon.t > self.now:
            self.now, self.llh = beacon.t, np.asarray(beacon.llh, float)
        self.captured.append((key, payload))

    # ----------------------------------------------------------------- liveliness churn
    def churn(self, dt: float) -> tuple[list[str], list[str]]:
        """The liveliness keys to declare and to withdraw over ``dt`` seconds."""
        n = int(self.rng.poisson(self.identities / 2 / self.token_life * dt))
        declare, withdraw = [], []
        for _ in range(n):
            name = f"H{self._next_token % self.identities}"
            self._next_token += 1
            if len(self.alive) >= self.identities // 2:
                withdraw.append(keys.alive("agent", self.alive.popleft()))
            self.alive.append(name)
            declare.append(keys.alive("agent", name))
        return declare, withdraw

    # ----------------------------------------------------------------- the flood
    #: forgeries prepared at a time, and how long [s of the fleet's time] they stay fresh
    POOL, POOL_LIFE = 512, 0.5

    def flood(self, n: int) -> list[tuple[str, bytes]]:
        """``n`` bad beacons as (key, payload), spread over the fleet's receivers and the kinds.
        Drawn from a pool of forgeries made again every :attr:`POOL_LIFE` seconds of the fleet's
        time (their times stay fresh), so that a flood of ten thousand a second costs the
        station little more than the sending."""
        if not self._pool or self.now - self._pool_t >= self.POOL_LIFE:
            self._refill()
        pick = self.rng.integers(len(self._pool), size=n)
        counts = np.bincount(self._pool_kind[pick], minlength=len(KINDS))
        for k, c in zip(KINDS, counts.tolist()):
            self.sent[k] += c
        pool = self._pool
        return [pool[i] for i in pick.tolist()]

    def _refill(self) -> None:
        rng = self.rng
        kinds = rng.integers(len(KINDS), size=self.POOL)
        self._pool = [self._one(KINDS[k], self.fleet[int(rng.integers(len(self.fleet)))]) for k in kinds.tolist()]
        self._pool_kind = kinds
        self._pool_t = self.now
        self._forged = {p for _, p in self._pool}
        # replays are drawn from what was heard last
        if self.captured:
            for i in np.flatnonzero(kinds == KINDS.index("replay")).tolist():
                self._pool[i] = self.captured[int(rng.integers(len(self.captured)))]

    def oversized(self) -> list[tuple[str, bytes]]:
        """One oversized payload to a receiver's radio, to the radio and to the recorder, the
        fleet's vehicles in turn (each is hit within as many rounds as there are vehicles)."""
        victim = self.fleet[self._big_rounds % len(self.fleet)]
        self._big_rounds += 1
        return [(keys.radio_rx(victim), self.big), (keys.radio_tx(victim), self.big),
                (keys.diag(victim), self.big)]

    def _one(self, kind: str, victim: str) -> tuple[str, bytes]:
        rx = keys.radio_rx(victim)
        if kind == "garbage":
            return rx, self.rng.bytes(int(self.rng.integers(1, 400)))
        if kind == "replay" and self.captured:
            return self.captured[int(self.rng.integers(len(self.captured)))]
        others = [v for v in self.fleet if v != victim] or self.fleet
        name = others[int(self.rng.integers(len(others)))]
        t = self.now
        auth = self.rng.bytes(AUTH_LEN)
        if kind == "stranger":
            name = f"H{int(self.rng.integers(self.identities))}"
        elif kind == "wrong_vehicle":
            wrong = [v for v in self.key_ids if v != name]
            if wrong:
                auth = self.key_ids[wrong[int(self.rng.integers(len(wrong)))]] + auth[KEY_ID_LEN:]
        elif kind == "unsigned":
            auth = b""
        elif kind in ("future", "stale"):
            # under the named vehicle's own key id (public): only the time window can shed it
            # before a signature would be verified
            auth = self.key_ids.get(name, auth[:KEY_ID_LEN]) + auth[KEY_ID_LEN:]
            t = self.now + 86400.0 if kind == "future" else self.now - 60.0
        self._seq += 1
        method = self.methods[int(self.rng.integers(len(self.methods)))]
        b = Beacon(name, self._seq, method, t, self.llh + self.rng.normal(0, 1e-5, 3) * (1, 1, 0), np.zeros(3),
                   np.eye(3), auth=auth)
        key = keys.radio_tx(name) if kind == "future" and self._seq % 2 else rx
        return key, encode(b)
