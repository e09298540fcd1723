"""Sequencer: measurements applied at their time inside IMU intervals, late and out-of-order
handling, and equivalence with propagating the unsplit intervals."""

from __future__ import annotations

import numpy as np
import pytest

from agent.sequencer import Apply, Propagate, Sequencer


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
