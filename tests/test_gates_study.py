"""``slcp scenario gates``: range-gate outcomes over seeds equal the sum of the single-seed
evaluations (two ways to compute the same thing), over a pool of processes."""

from __future__ import annotations

import json

import pytest

from slcp.deploy.cli import main

from conftest import short_scenario


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_gates_over_seeds_sum_the_single_seed_evaluations(capsys, tmp_path) -> None:
    # paper-1 to 25 s: by then V1 and V2 stand at the red light (V1 first, from about 18 s)
    scn = str(short_scenario(tmp_path, "paper-1", 25.0))
    assert main(["scenario", "gates", scn, "--seeds", "2", "--json"]) == 0
    pooled = json.loads(capsys.readouterr().out)
    assert pooled["seeds"] == [0, 1]
    want: dict = {}
    for seed in (0, 1):
        assert main(["scenario", "evaluate", scn, "--seed", str(seed), "--json"]) == 0
        for m, kinds in json.loads(capsys.readouterr().out)["ranges"].items():
            for kind, d in kinds.items():
                w = want.setdefault(m, {}).setdefault(kind, {"n": 0, "rejected": 0})
                w["n"] += d["n"]
                w["rejected"] += d["rejected"]
    got = {m: {k: {"n": d["n"], "rejected": d["rejected"]} for k, d in kinds.items()}
           for m, kinds in pooled["ranges"].items()}
    assert got == want
    cp = pooled["ranges"]["SL-CP"]
    assert cp["outlier"]["n"] > 0 and cp["clean"]["n"] > 1000  # the runs did range
    assert cp["clean"]["fused"] == cp["clean"]["outcomes"]["fused"]
    with pytest.raises(SystemExit):
        main(["scenario", "gates", "paper-1", "--seeds", "0"])
    assert "positive integer" in capsys.readouterr().err
