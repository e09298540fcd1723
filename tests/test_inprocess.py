"""All vehicles and methods in one process on the paper's scenarios (seed 0): first-stopped
detection never claims a vehicle that is not first, the stop line fixes the first stopped
vehicle, and cooperation helps."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.inprocess import run_inprocess
from hw_emulation.scenario import load_scenario
from hw_emulation.truth import build_truth


@pytest.fixture(scope="module", params=["paper-1", "paper-2"])
def run(request):
    truth = build_truth(load_scenario(request.param))
    return request.param, truth, run_inprocess(truth, seed=0)


def test_no_false_first_stopped_claims_and_stop_line_accuracy(run) -> None:
    name, truth, r = run
    claimed_any = []
    for vid, vt in truth.vehicles.items():
        true_first = vt.first_stopped[9::10][: len(r.t)]
        # detection latency tolerance: a claim may outlive the truth by up to 1 s (10 samples) when
        # the vehicle starts moving; no stop-line fix is applied then (needs >= 1 s stationary)
        ended = np.flatnonzero(true_first[:-1] & ~true_first[1:])
        for e in ended:
            true_first[e + 1: e + 11] = True
        for m in ("SL-SP", "SL-CP"):
            claims = r.first[(vid, m)]
            assert not (claims & ~true_first).any(), f"{name} {vid} {m}: false first-stopped claim"
            if claims.any():
                claimed_any.append(vid)
                rmse = float(np.sqrt(np.mean(r.err[(vid, "SL-SP")][r.first[(vid, "SL-SP")]] ** 2)))
                print(f"{name} {vid} {m}: SL-SP RMSE while first {rmse:.2f} m")
                # measured: paper-1 V1 0.26, paper-2 V0 0.11, V2 0.40 (lane ambiguous: along-only fix)
                assert rmse < 0.6
    expected = {"paper-1": {"V1"}, "paper-2": {"V0", "V2"}}[name]
    assert set(claimed_any) == expected


def test_cooperation_improves_the_fleet(run) -> None:
    """With the paper's fusion rule CP can make a good vehicle worse (double counting, issue #5);
    over the fleet it must help."""
    name, truth, r = run
    sp = cp = 0.0
    for vid in truth.vehicles:
        s = float(np.sqrt(np.mean(r.err[(vid, "SP")] ** 2)))
        c = float(np.sqrt(np.mean(r.err[(vid, "CP")] ** 2)))
        print(f"{name} {vid}: SP {s:.2f} CP {c:.2f}")
        sp, cp = sp + s, cp + c
    assert cp < sp


def test_cli_evaluate_json(capsys) -> None:
    import json

    from deploy.cli import main

    assert main(["scenario", "evaluate", "paper-1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    row = out["rows"][0]
    assert {"SP", "SL-SP", "CP", "SL-CP", "paper"} <= set(row)
    assert out["first_stopped"]["V1"]["claimed_while_not_first_s"] == 0.0
