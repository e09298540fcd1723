"""Misbehaving vehicles for the emulated V2V radio: the VeReMi attack types and an overconfident
covariance (pure functions of a beacon; SI units).

VeReMi (van der Heijden et al., 2018) falsifies the position (and, for the eventual stop, the
speed) of every beacon a misbehaving vehicle sends from the attack's start; here the attack acts
on the vehicle's own estimate as its agent sent it, the way a compromised on-board unit would:

===================  ==========================================================================
``constant_position``  a fixed position, drawn once in ``area`` around the map origin
``constant_offset``    the true estimate plus a fixed offset (VeReMi: Δx = 250 m, Δy = −150 m)
``random_position``    a new position drawn in ``area`` around the origin with every beacon
``random_offset``      the true estimate plus a new offset in [−70, 70] m per axis every beacon
``eventual_stop``      from the start on, the position of that moment and zero velocity
``overconfident``      the true estimate with its covariance shrunk by ``shrink`` (1e-4: σ / 100)
===================  ==========================================================================

The attacker keeps signing with its own (valid) key: these are insider attacks, which signatures
cannot stop and misbehaviour detection must.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from slcp.geo import earth
from slcp.transport.messages import Beacon

ATTACKS = ("constant_position", "constant_offset", "random_position", "random_offset", "eventual_stop",
           "overconfident")


@dataclass
class Attack:
    """One misbehaving vehicle.

    Attributes
    ----------
    vehicle : str
    kind : str
        One of :data:`ATTACKS`.
    start : float
        Sensor time [s] from which its beacons are falsified.
    offset_ne : tuple
        Constant offset (north, east) [m].
    random_offset : float
        Half-width of the random offset per axis [m].
    area : float
        Half-width of the square (around the map origin) of random and constant positions [m].
    shrink : float
        Covariance factor of the overconfident attack.
    """

    vehicle: str
    kind: str
    start: float
    offset_ne: tuple[float, float] = (-150.0, 250.0)
    random_offset: float = 70.0
    area: float = 200.0
    shrink: float = 1e-4
    _frozen: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in ATTACKS:
            raise ValueError(f"unknown attack {self.kind!r}; known: {', '.join(ATTACKS)}")

    @classmethod
    def parse(cls, text: str) -> Attack:
        """``VEHICLE:KIND@START`` (e.g. ``V2:random_offset@12``)."""
        try:
            who, rest = text.split(":", 1)
            kind, start = rest.split("@", 1)
            return cls(who, kind, float(start))
        except ValueError as exc:
            raise ValueError(f"attack {text!r}: expected VEHICLE:KIND@START_S ({exc})") from None

    def apply(self, b: Beacon, origin_llh, rng: np.random.Generator) -> Beacon:
        """The beacon as the misbehaving vehicle sends it (unchanged before ``start``)."""
        if b.vehicle != self.vehicle or b.t < self.start:
            return b
        k = self.kind
        if k == "overconfident":
            return dataclasses.replace(b, cov_pos=b.cov_pos * self.shrink)
        if k == "constant_offset":
            return dataclasses.replace(b, llh=earth.offset_llh(b.llh, np.array([*self.offset_ne, 0.0])))
        if k == "random_offset":
            d = rng.uniform(-self.random_offset, self.random_offset, 2)
            return dataclasses.replace(b, llh=earth.offset_llh(b.llh, np.array([d[0], d[1], 0.0])))
        if k == "random_position":
            d = rng.uniform(-self.area, self.area, 2)
            return dataclasses.replace(
                b, llh=earth.offset_llh(np.asarray(origin_llh, float), np.array([d[0], d[1], 0.0]))
            )
        if k == "constant_position":
            if "llh" not in self._frozen:
                d = rng.uniform(-self.area, self.area, 2)
                self._frozen["llh"] = earth.offset_llh(np.asarray(origin_llh, float), np.array([d[0], d[1], 0.0]))
            return dataclasses.replace(b, llh=self._frozen["llh"].copy())
        # eventual stop: the position of the first falsified beacon, standing still
        llh = self._frozen.setdefault("llh", b.llh.copy())
        return dataclasses.replace(b, llh=llh.copy(), v_ned=np.zeros(3))
