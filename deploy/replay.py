"""Replay a recorded drive through the vehicle engine (SP) with simulated GNSS outages.

The drive becomes the messages a vehicle's sensor drivers would publish
(:func:`deploy.replay_publish.plan_drive`: IMU batches with the mounting rotation and time
offset applied, GNSS fixes with ellipsoidal heights, the fixes inside the outages withheld),
and the engine a vehicle runs (:class:`agent.engine.VehicleEngine`) takes them; its estimates
are scored against the file's fixes at their epochs. ``slcp replay --publish`` plays the same
messages to a live agent and scores the same way.

The outage protocol is the one the rtklibexplorer data's authors use: with ``t0`` the first GNSS
epoch and ``tN`` the last, outage ``k`` withholds the fixes in ``[S_k, S_k + length)`` with
``S_k = t0 + first + period * k`` for every ``k`` with ``S_k < tN - end_margin``. The engine is
causal: nothing is smoothed backwards.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from slcp.agent.engine import AgentConfig, VehicleEngine
from slcp.transport.messages import Estimate
from slcp.vehicles.profile import VehicleProfile

from .datasets.recording import Recording
from .drive_scoring import score_estimates

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OutageProtocol:
    """Simulated GNSS outages [s]; ``length = 0`` disables them."""

    first: float = 40.0
    period: float = 45.0
    length: float = 15.0
    end_margin: float = 30.0

    def windows(self, t0: float, t_end: float) -> list[tuple[float, float]]:
        """Outage windows ``[start, end)`` in absolute time."""
        if self.length <= 0:
            return []
        if self.period <= 0:
            raise ValueError("outage period must be positive")
        out = []
        k = 0
        while (s := t0 + self.first + self.period * k) < t_end - self.end_margin:
            out.append((s, s + self.length))
            k += 1
        return out


@dataclass(frozen=True)
class ReplayConfig:
    """A replay: the recording's vehicle (its profile: mount, time offset, heights, noise,
    constraints) and the outage protocol. Without a profile the vehicle is a generic one
    (:class:`vehicles.profile.VehicleProfile`'s defaults)."""

    profile: VehicleProfile = VehicleProfile()
    outage: OutageProtocol = OutageProtocol()


#: the share of RTK-fixed epochs from which a recording's fixes are its reference: below it, the
#: outage figures would score the filter against a receiver no better than itself
REFERENCE_SHARE = 0.5


def reference_share(gnss) -> float:
    """The share of ``gnss``'s epochs that are RTK-fixed (quality 1)."""
    return float(np.mean(np.asarray(gnss.quality) == 1)) if len(gnss.quality) else 0.0


@dataclass
class ReplayResult:
    """Per-epoch evaluation and the engine's trajectory; ``t0`` is the first GNSS epoch [s]."""

    t: np.ndarray
    h_err: np.ndarray
    withheld: np.ndarray
    outages: list[tuple[float, float]]
    trajectory: np.ndarray
    t0: float = 0.0
    metrics: dict = field(default_factory=dict)


TRAJECTORY_COLUMNS = (
    "time_gpst_s", "lat_deg", "lon_deg", "h_m", "vn_mps", "ve_mps", "vd_mps",
    "roll_deg", "pitch_deg", "yaw_deg", "sigma_n_m", "sigma_e_m", "sigma_d_m",
)


def run_replay(drive: Recording, cfg: ReplayConfig = ReplayConfig(), vehicle: str = "V0", start: float = 0.0,
               duration: float | None = None) -> ReplayResult:
    """The drive's messages through the vehicle engine (SP), scored at the GNSS epochs; from
    ``start`` seconds after the first GNSS epoch for ``duration`` seconds (None: to the end)."""
    from .replay_publish import plan_drive

    wall0 = time.perf_counter()
    plan = plan_drive(drive, vehicle, cfg, start, duration)
    engine = VehicleEngine(engine_config(cfg, vehicle))
    est: list[Estimate] = []
    for _, _, msg in plan.messages:
        engine.handle(msg)
        est += [o for o in engine.take_outbox() if isinstance(o, Estimate)]
    engine.finish()
    est += [o for o in engine.take_outbox() if isinstance(o, Estimate)]
    if not est:
        raise ValueError("the engine never started: no GNSS fix within a second of the IMU data")
    wall = time.perf_counter() - wall0
    figures, inside, err = score_estimates(plan.fix_t, plan.fix_llh, plan.withheld, est,
                                           cfg.profile.gnss.lever_arm_m)
    t0 = float(drive.gnss.t[0])
    outages = cfg.outage.windows(t0, float(drive.gnss.t[-1]))
    res = ReplayResult(plan.fix_t[inside], err, plan.withheld[inside], outages, _trajectory(est), t0)
    imu_span = float(plan.messages[-1][0] - plan.messages[0][0])  # the replayed span
    res.metrics = {**{k: (float("nan") if v is None else v) for k, v in figures.items()},
                   "imu_span_s": imu_span, "wall_s": wall,
                   "realtime_factor": imu_span / wall if wall > 0 else float("inf")}
    f = engine.filters["SP"]
    res.metrics["imu_time_offset_s"] = cfg.profile.time.imu_offset_s + f.time_offset
    st = f.filter.stats
    res.metrics["filter_stats"] = {"imu_samples": st.imu_samples, "cov_steps": st.cov_steps,
                                   "updates": st.updates, "rejected": st.rejected}
    return res


def _trajectory(est: list[Estimate]) -> np.ndarray:
    """The estimates as rows of :data:`TRAJECTORY_COLUMNS`."""
    rows = []
    for e in est:
        rpy = np.degrees(e.rpy)
        sig = np.sqrt(np.maximum(np.diag(e.cov_pos), 0.0))
        rows.append([e.t, math.degrees(e.llh[0]), math.degrees(e.llh[1]), e.llh[2], *e.v_ned, *rpy, *sig])
    return np.array(rows).reshape(-1, len(TRAJECTORY_COLUMNS))


def phase_protocols(protocol: OutageProtocol, n: int) -> list[OutageProtocol]:
    """The outage protocol at ``n`` phases evenly spread over its period: the first outage
    starts at ``first + k · period / n`` for k = 0 … n − 1 (k = 0 is ``protocol`` itself), so
    the outages of all phases together cover the drive evenly."""
    if n < 1:
        raise ValueError("the number of phases must be at least 1")
    return [dataclasses.replace(protocol, first=protocol.first + k * protocol.period / n) for k in range(n)]


def pooled_metrics(results: list[ReplayResult]) -> dict:
    """Outage metrics over several replays of one drive (e.g. at the :func:`phase_protocols`):
    the RMS over every withheld fix of every run, the end-of-outage mean and max over every
    outage, the largest error; and each run's own figures under ``phases`` (``first_outage_s``
    after t0, [s]). Errors in metres."""
    withheld = np.concatenate([r.h_err[r.withheld] for r in results])
    ends = [e for r in results for e in r.metrics["outage_end_errors_m"]]
    phases = [{"first_outage_s": (r.outages[0][0] - r.t0) if r.outages else None,
               **{k: r.metrics[k] for k in ("n_outages", "n_withheld_fixes", "outage_h_rms_m",
                                            "outage_h_end_mean_m", "outage_h_end_max_m", "outage_h_max_m")}}
              for r in results]
    return {
        "n_phases": len(results),
        "n_outages": len(ends),
        "n_withheld_fixes": int(withheld.size),
        "outage_h_rms_m": float(np.sqrt(np.mean(np.square(withheld)))) if withheld.size else float("nan"),
        "outage_h_end_mean_m": float(np.mean(ends)) if ends else float("nan"),
        "outage_h_end_max_m": float(np.max(ends)) if ends else float("nan"),
        "outage_h_max_m": float(np.max(withheld)) if withheld.size else float("nan"),
        "phases": phases,
    }


def engine_config(cfg: ReplayConfig, vehicle: str = "V0") -> AgentConfig:
    """The vehicle engine's configuration for a replay: a vehicle without a site map running
    SP, with the profile's IMU model, installation and options."""
    from .agent_configs import siteless_agent_config, with_profile

    return with_profile(siteless_agent_config(vehicle, ("SP",)), cfg.profile)
