"""Neighbour table: extrapolation, covariance growth, staleness, duplicates, time-out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.neighbours import NeighbourTable
from slcp.geo import earth

LLH = np.array([math.radians(39.95), math.radians(116.32), 50.0])


def test_extrapolation_and_covariance_growth() -> None:
    tab = NeighbourTable(sigma_v=0.5, accel_psd=1.0)
    assert tab.update("V2", 1, 10.0, LLH, np.array([10.0, 0.0, 0.0]), np.eye(3), "SP", now=10.01)
    s = tab.at("V2", 10.2)
    d = earth.ned_offset(*s.llh, *LLH)
    assert d == pytest.approx([2.0, 0.0, 0.0], abs=1e-6)  # 0.2 s at 10 m/s north
    grow = 0.04 * 0.25 + 0.008 / 3
    assert np.allclose(s.cov_ned, np.eye(3) * (1 + grow))
    assert s.age == pytest.approx(0.2)


def test_the_breakdown_by_source_grows_with_the_sender_and_must_add_up() -> None:
    """The extrapolation's growth is the sender's own; a breakdown that does not add up to the
    covariance is dropped (the estimate counts as of unknown composition) and counted."""
    tab = NeighbourTable(sigma_v=0.5, accel_psd=1.0)
    split = ((("V2",), 0.75 * np.eye(3)), (("~common", "V0"), 0.25 * np.eye(3)))
    tab.update("V2", 1, 10.0, LLH, np.zeros(3), np.eye(3), "SL-CP", now=10.0, sources=split)
    s = tab.at("V2", 10.2)
    grow = 0.04 * 0.25 + 0.008 / 3
    assert [set(lab) for lab, _ in s.sources] == [{"V2"}, {"V0", "~common"}]
    assert np.allclose(s.sources[0][1], (0.75 + grow) * np.eye(3)) and np.allclose(s.sources[1][1], 0.25 * np.eye(3))
    assert np.allclose(sum(c for _, c in s.sources), s.cov_ned)
    tab.update("V2", 2, 10.1, LLH, np.zeros(3), 2.0 * np.eye(3), "SL-CP", now=10.1, sources=split)
    assert tab.counters["sources_dropped"] == 1 and tab.at("V2", 10.1).sources == ()
    # exactly tracked constants complete the sum; without them it does not add up
    g = np.array([0.6, 0.0, 0.0])
    cov = np.eye(3) + np.outer(g, g)
    tab.update("V2", 3, 10.2, LLH, np.zeros(3), cov, "SL-CP", now=10.2, sources=split, constants=(("V2~1.0", g),))
    s = tab.at("V2", 10.2)
    assert tab.counters["sources_dropped"] == 1 and len(s.sources) == 2
    assert [lab for lab, _ in s.constants] == ["V2~1.0"] and np.allclose(s.constants[0][1], g)
    tab.update("V2", 4, 10.3, LLH, np.zeros(3), cov, "SL-CP", now=10.3, sources=split)
    assert tab.counters["sources_dropped"] == 2 and tab.at("V2", 10.3).constants == ()


def test_stale_duplicate_and_timeout() -> None:
    tab = NeighbourTable(max_age=0.3, timeout=2.0)
    tab.update("V2", 5, 10.0, LLH, np.zeros(3), np.eye(3), "SP", now=10.0)
    assert tab.at("V2", 10.31) is None and tab.counters["stale"] == 1
    assert not tab.update("V2", 5, 10.0, LLH, np.zeros(3), np.eye(3), "SP", now=10.2)   # duplicate
    assert not tab.update("V2", 6, 9.9, LLH, np.zeros(3), np.eye(3), "SP", now=10.2)    # older time
    assert not tab.update("V2", 7, 10.0, LLH, np.zeros(3), np.eye(3), "SP", now=10.2)   # replay, new seq
    assert tab.counters["duplicate_or_old"] == 3
    # a restarted sender counts its sequence from 0 again: its newer beacons are taken
    assert tab.update("V2", 0, 10.1, LLH, np.zeros(3), np.eye(3), "SP", now=10.1)
    assert tab.expire(12.0) == [] and tab.expire(12.2) == ["V2"]
    assert tab.at("V2", 12.2) is None and tab.vehicles() == []


def test_thousands_of_lost_neighbours_keep_the_diagnostics_decodable() -> None:
    """#39 finding 4: each departure was remembered for ever and sent whole in every diagnostics
    message, which the codec refuses past 256 entries. The engine keeps the latest MAX_LOST and
    counts the rest."""
    from slcp.agent.engine import VehicleEngine
    from slcp.deploy.agent_configs import siteless_agent_config
    from slcp.transport.codec import decode, encode

    eng = VehicleEngine(siteless_agent_config("V0", ("SP",)))
    for k in range(3000):
        eng.neighbour_alive(f"N{k}", True)
        eng.neighbour_alive(f"N{k}", False)
    assert len(eng.lost) == VehicleEngine.MAX_LOST and "N2999" in eng.lost and "N0" not in eng.lost
    assert eng.counters["neighbour_lost_forgotten"] == 3000 - VehicleEngine.MAX_LOST
    diag = decode(encode(eng.diagnostics(0.0)))
    assert len(diag.status["lost"]) == VehicleEngine.MAX_LOST
