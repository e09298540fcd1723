"""A method's cooperative range updates: gates, node selection and the fusion rules
(:class:`RangeUpdates`, one part of :class:`agent.methods.MethodFilter`)."""

from __future__ import annotations

import math

import numpy as np

from slcp.geo import earth

from .nav.ins_filter import InsFilter
from .nav.kalman import Measurement, UpdateResult
from .nav.measurements.common import NO_LEVER_ARM
from .nav.measurements.v2v_range import quadratic_rows, range_measurement, relative_position
from .nav.source_fusion import ANY, SourcePart
from .nav.state import POS
from .neighbours import NeighbourState
from .range_geometry import STANDING_SPEED, rate_variance, too_near
from .settings import FilterSettings, MethodSpec


class RangeUpdates:
    """The range part of a method's filter: the UWB range to a neighbour weighed against the
    neighbour's beacon by the configured fusion rule, behind the physical, rate, NIS and NLOS
    gates and node selection."""

    filter: InsFilter
    settings: FilterSettings
    spec: MethodSpec
    vehicle: str
    counters: dict[str, int]

    def range(self, neighbour: NeighbourState, measured: float, t: float | None = None) -> str | None:
        """Fuse a UWB range [m] to a neighbour, measured at sensor time ``t`` [s] (default: now;
        earlier for a range deferred until the neighbour's beacon of that time arrived).

        Returns the outcome: ``"fused"``; ``"skipped"`` (node selection: too little expected
        gain); ``"skipped_near"`` (too near for the linearisation: ``range_min_sigmas``);
        ``"gate_physical"`` (outside (0, max_range)); ``"gate_rate"`` (a jump the
        vehicles' motion cannot explain); ``"gate_nlos"`` (more probably NLOS than not, CI
        rules with an NLOS model); ``"gate_nis"`` (χ² innovation gate); None for methods
        without ranges.
        """
        if not self.spec.ranges:
            return None
        s = self.settings
        t_meas = self.t if t is None else t
        if not 0.0 < measured < s.max_range:
            return self._count_range("gate_physical")
        nb_llh = neighbour.llh
        if t_meas < self.t:
            # a delayed range: move the neighbour by my displacement since t, which keeps the
            # relative geometry of time t while the Jacobian acts on my current error
            nb_llh = earth.offset_llh(nb_llh, self.displacement_since(t_meas))
        d = relative_position(self.filter.state, NO_LEVER_ARM, nb_llh)  # the UWB antenna at the IMU
        # the line of sight as the range model takes it: horizontal unless the 3-D model is
        # chosen (Python floats: a dozen numpy calls on 3-vectors cost more than the arithmetic)
        d0, d1, d2 = d.tolist()
        l2 = 0.0 if s.range_height_sigma is not None else d2
        norm = max(math.sqrt(d0 * d0 + d1 * d1 + l2 * l2), 1e-3)
        u = (d0 / norm, d1 / norm, l2 / norm)
        vi, vj = self.filter.state.v.tolist(), neighbour.v_ned.tolist()
        v_rel = (vi[0] - vj[0], vi[1] - vj[1], vi[2] - vj[2])
        rate = u[0] * v_rel[0] + u[1] * v_rel[1] + u[2] * v_rel[2]
        if not self.rate_gate.check(neighbour.vehicle, t_meas, measured, rate):
            return self._count_range("gate_rate")
        own_cov = self.filter.position_cov
        own_rows, nb_rows = own_cov.tolist(), neighbour.cov_ned.tolist()
        link = None
        if self.nlos_tracker is not None:
            speed2 = v_rel[0] ** 2 + v_rel[1] ** 2
            link = self.nlos_tracker.belief(
                neighbour.vehicle, t_meas, measured, rate, speed2,
                standing=vi[0] ** 2 + vi[1] ** 2 < STANDING_SPEED**2 and vj[0] ** 2 + vj[1] ** 2 < STANDING_SPEED**2,
                rate_var=rate_variance(u, (d0, d1, d2), own_rows, nb_rows, speed2))
            if link.outlier:
                return self._count_range("gate_rate")
        if s.range_min_sigmas > 0.0 and too_near((d0, d1, d2), own_rows, nb_rows, s.range_min_sigmas):
            return self._count_range("skipped_near")
        m = range_measurement(self.filter.state, measured, s.sigma_uwb, nb_llh, neighbour.cov_ned,
                              own_cov_ned=own_cov, second_order=s.second_order_ranges,
                              relative=d, height_offset=None if s.range_height_sigma is None
                              else (0.0, s.range_height_sigma))
        if s.fusion == "paper":
            res = self.filter.update(m, s.range_gate)
        else:
            res = self._range_ci(m, neighbour, t_meas, own_rows, nb_rows, u, link)
            if isinstance(res, str):
                return self._count_range(res)
        return self._count_range("skipped" if res.skipped else "fused" if res.accepted else "gate_nis")

    def _range_ci(self, m: Measurement, neighbour: NeighbourState, t_meas: float, own_rows: list, nb_rows: list,
                  u: tuple[float, float, float], link) -> UpdateResult | str:
        """A range under a CI rule: the NLOS and NIS gates on the whole spread, node selection
        held for a declined neighbour, then the update; an outcome string when gated."""
        s = self.settings
        # innovation and its variance HPHᵀ + R: the model's row acts on the position only
        nu = -float(m.z[0])
        hp = m.H[0, POS].tolist()
        var = quadratic_rows(own_rows, hp) + float(m.R[0, 0])
        if s.uwb_nlos is not None and s.uwb_nlos.classify(nu, var, s.nlos_reject_probability,
                                                          None if link is None else link.p_nlos):
            return "gate_nlos"
        r_bias = s.uwb_nlos_sigma**2 if link is None else link.bias_variance
        # the NIS gate on the whole spread, uninflated: the split-CI update gates on its
        # inflated covariances, P/ω and R_dep/(1-ω), and when most of P is shared with the
        # neighbours ω is small and a gross outlier passes, and moves the vehicle (and through
        # its beacons, its neighbours) by tens of metres
        if self._range_gate_nis is not None and nu * nu / max(var + r_bias, 1e-12) > self._range_gate_nis:
            return "gate_nis"
        own_var, nb_var = own_rows[0][0] + own_rows[1][1], nb_rows[0][0] + nb_rows[1][1]
        if self._decline_held(neighbour.vehicle, t_meas, own_var, nb_var, u):
            self.counters["ranges_skipped_held"] += 1
            return "skipped"
        # the neighbour's estimate is wholly dependent: it may contain our information, and
        # its own-sensor errors (multipath) persist from one range to the next; so does an
        # NLOS bias. The UWB white noise (and the second-order term) is independent.
        h = m.H[0, POS]  # the line of sight as the model uses it (horizontal or 3-D)
        r_nb = max(quadratic_rows(nb_rows, hp), 0.0)
        m_ind = Measurement(m.z, m.H, m.R - r_nb, m.name)
        if s.fusion == "source-ci":
            res = self._range_source_ci(m_ind, h, neighbour, r_nb, r_bias)
        else:
            r_dep = np.array([[r_nb + r_bias]])
            res = self.filter.update_split_ci(m_ind, r_dep, own_independent=s.fusion == "split-ci",
                                              gate_probability=s.range_gate, min_gain=s.min_gain)
        if res.skipped and s.selection_hold > 0.0:
            horiz = max(math.hypot(u[0], u[1]), 1e-9)
            self._declined[neighbour.vehicle] = (t_meas, own_var, nb_var, u[0] / horiz, u[1] / horiz)
        else:
            self._declined.pop(neighbour.vehicle, None)
        return res

    def _decline_held(self, vehicle: str, t: float, own_var: float, nb_var: float,
                      u: tuple[float, float, float]) -> bool:
        """Whether node selection's last decline of ``vehicle`` still holds for a range at sensor
        time ``t`` [s] (``selection_hold``): recent enough, and neither the own (``own_var``) nor
        the neighbour's (``nb_var``) horizontal position variance [m²] nor the line of sight
        ``u`` (unit, NED; its horizontal direction) moved by more than the settings allow."""
        last = self._declined.get(vehicle)
        if last is None:
            return False
        s = self.settings
        t0, own0, nb0, e0, n0 = last
        if not 0.0 <= t - t0 < s.selection_hold:
            return False
        if own_var > own0 * (1.0 + s.selection_hold_change) or nb_var < nb0 * (1.0 - s.selection_hold_change):
            return False
        # the turn of the horizontal line of sight: cos of the angle between the two directions
        horiz = math.hypot(u[0], u[1])
        return horiz > 0.0 and (u[0] * e0 + u[1] * n0) / horiz >= math.cos(s.selection_hold_turn)

    def _range_source_ci(self, m: Measurement, h: np.ndarray, neighbour: NeighbourState,
                         r_nb: float, r_bias: float) -> UpdateResult:
        """A range's source-CI update (:mod:`agent.nav.source_fusion`). ``m`` carries the range's
        white noise; the neighbour's estimate enters by source (its beacon's breakdown, projected
        on the line of sight ``h`` (3,); ``r_nb`` [m²] the whole of it projected, used when the
        beacon has no breakdown), and the link's NLOS bias ``r_bias`` [m²] under the
        link's name. Both ends of a link receive the same range, so its noise is a source of its
        own, named after the link (``"V0|V1"``) at both ends. A beacon no older than the range may
        already hold this very range: its white noise then counts with the link's source too."""
        link = frozenset({"|".join(sorted((self.vehicle, neighbour.vehicle)))})
        if neighbour.source_labels:
            var = np.maximum((neighbour.source_cov @ h) @ h, 0.0).tolist()
            parts = [SourcePart(lab, v) for lab, v in zip(neighbour.source_labels, var)]
        else:  # no breakdown: the neighbour's estimate may hold anything
            parts = [SourcePart(frozenset({ANY}), r_nb)]
        if r_bias > 0.0:
            parts.append(SourcePart(link, r_bias, correlated=True))
        if neighbour.age <= 0.0:
            white = float(m.R[0, 0])
            parts.append(SourcePart(link, white, correlated=True))
            m = Measurement(m.z, m.H, np.zeros((1, 1)), m.name)
        s = self.settings
        # the neighbour's position error enters the range opposite to mine: -h
        constants = [(lab, -float(g @ h)) for lab, g in neighbour.constants]
        return self.filter.update_source_ci(m, parts, link, s.range_gate, s.min_gain, constants,
                                            s.ci_velocity_horizon)

    def _count_range(self, outcome: str) -> str:
        self.counters["ranges" if outcome == "fused" else f"ranges_{outcome}"] += 1
        if outcome.startswith("gate"):
            self.counters["ranges_rejected"] += 1
        return outcome

