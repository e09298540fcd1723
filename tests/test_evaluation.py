"""A run's evaluation from its recording alone (`deploy.run_report.evaluate_recording`): the
scenario's windows and each vehicle's standing window, scored against truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slcp.deploy.run_report import evaluate_recording
from slcp.geo import earth
from slcp.hw_emulation.scenario import STANDING_WINDOW, load_scenario
from slcp.hw_emulation.truth import build_truth


def _estimate(vid: str, method: str, t: float, llh, north: float, sigma: float) -> dict:
    """An estimate ``north`` [m] north of ``llh`` with a horizontal σ of ``sigma`` per axis."""
    lat = llh[0] + north / earth.radii(llh[0])[0]
    return {"type": "Estimate", "vehicle": vid, "method": method, "t": t, "llh": [lat, llh[1], llh[2]],
            "v_ned": [0.0, 0.0, 0.0], "rpy": [0.0, 0.0, 0.0], "first_stopped": False,
            "cov_pos": [[sigma**2, 0.0, 0.0], [0.0, sigma**2, 0.0], [0.0, 0.0, 1.0]]}


@pytest.mark.timeout(120)
def test_the_standing_window_scores_the_times_a_vehicle_truly_stands(tmp_path) -> None:
    """Estimates 0.3 m off (σ 0.3 m) while the vehicle truly stands and 1.2 m off otherwise: the
    standing window holds exactly the standing records, its RMSE is 0.3 m and its NEES 1; a
    vehicle that never stands has no standing cell. Two ways to the same count: the truth's own
    standing flags at the record times."""
    truth = build_truth(load_scenario("paper-1"), stop_seed=0)
    (tmp_path / "estimates").mkdir()
    lines, expected = [], {}
    for vid, vt in truth.vehicles.items():
        tr = vt.truth
        n_standing = 0
        for t in np.arange(tr.t[0] + 0.2, tr.t[-1], 0.2):
            k = min(int(np.searchsorted(tr.t, t - 1e-9)), len(tr.t) - 1)
            stands = bool(vt.stopped[k])
            n_standing += stands
            lines.append(json.dumps(_estimate(vid, "SL-SP", float(t), tr.llh[k].tolist(), 0.3 if stands else 1.2, 0.3)))
        expected[vid] = n_standing
    rec = tmp_path / "messages.jsonl"
    rec.write_text("\n".join(lines) + "\n")
    m = evaluate_recording(truth, rec, tmp_path, ("SL-SP",))
    assert list(m["rmse"])[:len(truth.scenario.windows)] == list(truth.scenario.windows)
    rows = m["rmse"][STANDING_WINDOW]
    assert {v for v, n in expected.items() if n} == set(rows) and set(rows) < set(truth.vehicles)
    for vid, cells in rows.items():
        c = cells["SL-SP"]
        assert c["n"] == expected[vid]
        assert c["rmse_m"] == pytest.approx(0.3, abs=1e-3)
        assert c["nees_h"] == pytest.approx(1.0, abs=0.02)
        assert c["bound_rms_m"] > 0.0
    # the scenario's window mixes standing and driving records
    w = m["rmse"]["t_s1-t_e"]["V2"]["SL-SP"]
    assert 0.3 + 1e-3 < w["rmse_m"] < 1.2 - 1e-3 and math.isfinite(w["nees_h"])
