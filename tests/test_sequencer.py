"""Sequencer: measurements applied at their time inside IMU intervals, late and out-of-order
handling, and equivalence with propagating the unsplit intervals."""

from __future__ import annotations

import numpy as np
import pytest

from slcp.agent.sequencer import Apply, Propagate, Sequencer


def _run(seq, intervals):
    out = []
    for t_end, th, dv, dt in intervals:
        out.extend(seq.imu(t_end, th, dv, dt))
    return out


def test_split_at_measurement_times_preserves_the_increments() -> None:
    seq = Sequencer()
    ivs = [(0.01 * (k + 1), (0.001 * k, 0.0, 0.01), (0.1, 0.0, -0.098), 0.01) for k in range(10)]
    for t in (0.035, 0.05, 0.0351):
        assert seq.push(t, "gnss", t) == []
    steps = _run(seq, ivs)
    applies = [s for s in steps if isinstance(s, Apply)]
    assert [a.payload for a in applies] == [0.035, 0.0351, 0.05]
    assert [a.t for a in applies] == pytest.approx([0.035, 0.0351, 0.05])
    props = [s for s in steps if isinstance(s, Propagate)]
    assert sum(p.dt for p in props) == pytest.approx(0.1)
    total = np.sum([p.dtheta for p in props], axis=0)
    assert total == pytest.approx(np.sum([iv[1] for iv in ivs], axis=0))
    # the time at each Apply equals the time integrated so far
    t = 0.0
    for s in steps:
        if isinstance(s, Propagate):
            t += s.dt
        else:
            assert s.t == pytest.approx(t)


def test_late_and_out_of_order() -> None:
    seq = Sequencer(late_tolerance=0.05)
    list(seq.imu(1.0, (0, 0, 0), (0, 0, 0), 0.01))
    assert seq.push(0.97, "uwb", 1) == [Apply(1.0, "uwb", 1)]  # 30 ms late: applied now
    assert seq.push(0.5, "uwb", 2) == []                         # 500 ms late: dropped
    assert seq.counters["late_applied"] == 1 and seq.counters["late_dropped"] == 1
    assert list(seq.imu(0.99, (0, 0, 0), (0, 0, 0), 0.01)) == [] and seq.counters["imu_out_of_order"] == 1
    list(seq.imu(2.0, (0, 0, 0), (0, 0, 0), 0.01))
    assert seq.counters["imu_gaps"] == 1
    small = Sequencer(max_pending=2)
    for t in (5.0, 6.0, 7.0):
        small.push(t, "g", t)
    assert small.counters["overflow"] == 1


def test_plain_interval_fast_path_equals_the_general_one() -> None:
    """``imu_plain`` (no measurement inside the interval) advances the clock, counts gaps and
    out-of-order samples, and absorbs jitter exactly as :meth:`Sequencer.imu` does."""
    rng = np.random.default_rng(3)
    a, b = Sequencer(), Sequencer()
    t = 10.0
    for k in range(300):
        dt = 0.01 + rng.normal(0.0, 2e-4)
        t += 0.3 if k == 150 else dt  # one data gap
        if k == 200:
            t -= 0.05                 # one sample behind the clock
        th, dv = tuple(rng.normal(0, 1e-3, 3)), tuple(rng.normal(0, 1e-2, 3))
        steps = list(a.imu(t, th, dv, dt))
        assert not b.pending_by(t)
        span = b.imu_plain(t, dt)
        if not steps:
            assert span is None
        else:
            (p,) = steps
            assert span == pytest.approx(p.dt, abs=1e-15) and p.dtheta == pytest.approx(th)
        assert a.t == b.t
    assert a.counters == b.counters and a.counters["imu_gaps"] == 1 and a.counters["imu_out_of_order"] >= 1
    b.push(b.t + 0.005, "gnss", None)
    assert b.pending_by(b.t + 0.01) and not b.pending_by(b.t + 0.001)
