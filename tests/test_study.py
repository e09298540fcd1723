"""Multi-seed study aggregation: mean ± sd, ANEES band, pooled detection (synthetic runs)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from slcp.deploy.study import aggregate, anees_band, paired_difference, study_markdown

from conftest import short_scenario


def test_anees_band_matches_the_chi_square_table() -> None:
    assert anees_band(25) == pytest.approx((1.29, 2.86), abs=0.01)
    assert anees_band(50) == pytest.approx((1.48, 2.59), abs=0.01)


def test_aggregate_over_seeds(tmp_path) -> None:
    per_seed = {}
    for s, (rmse, nees) in enumerate([(1.0, 1.5), (3.0, 2.5)]):
        d = tmp_path / f"seed-{s}" / "estimates"
        d.mkdir(parents=True)
        (d / "V1.csv").write_text("time_s,method,nees_h\n" + "".join(f"{0.1 * k:.1f},SP,{nees}\n" for k in range(10)))
        per_seed[s] = {
            "scenario": "x",
            "rmse": {"w": {"V1": {"SP": {"rmse_m": rmse, "along_rmse_m": rmse / 2, "cross_rmse_m": rmse / 3,
                                         "nees_h": nees + 1.0, "n": 10 + 30 * s},
                                  "CP": {"rmse_m": rmse - 0.5 - 0.1 * s, "along_rmse_m": 0.0, "cross_rmse_m": 0.0}}}},
            "first_stopped": {"V1": {"SL-SP": {"truth_s": 10.0, "claimed_s": 9.0, "wrong_s": 0.5 * s,
                                               "covered_s": 9.0 - 0.5 * s, "latency_s": [0.2 + s]}}},
        }
    st = aggregate(tmp_path, per_seed)
    c = st["rmse"]["w"]["V1"]["SP"]
    assert c["mean_rmse_m"] == pytest.approx(2.0) and c["sd_rmse_m"] == pytest.approx(np.sqrt(2.0))
    cp = st["paired"]["w"]["V1"]["CP - SP"]  # differences -0.5, -0.6 over the two seeds
    assert cp["mean_m"] == pytest.approx(-0.55) and cp["n_seeds"] == 2 and cp["verdict"] == "n.s."
    assert "SL-CP - SP" not in st["paired"]["w"]["V1"]  # a method no seed ran is not compared
    # the window's ANEES weighs each seed by its estimates: (2.5·10 + 3.5·40) / 50
    wa = st["rmse"]["w"]["V1"]["SP"]["anees"]
    assert wa["anees"] == pytest.approx(3.3) and wa["band"] == list(anees_band(2)) and wa["inside"] is True
    assert "anees" not in st["rmse"]["w"]["V1"]["CP"]  # no NEES in the seeds' metrics: none made up
    md = study_markdown(SimpleNamespace(name="x", paper_table={}), st)
    assert f"| V1 | -0.55 ± {cp['half_width_m']:.2f} n.s. | – | – | – |" in md
    assert "<br>ANEES 3.30" in md
    assert st["anees"]["V1/SP"]["anees"] == pytest.approx(2.0)
    assert st["anees"]["V1/SP"]["inside"] is True  # 2 runs: band 0.24-5.57
    lo, hi = anees_band(2)
    assert st["anees"]["V1/SP"]["band"] == [lo, hi]
    d = st["first_stopped"]["V1/SL-SP"]
    assert d["precision"] == pytest.approx(1 - 0.5 / 18) and d["recall"] == pytest.approx(17.5 / 20)
    assert d["mean_latency_s"] == pytest.approx(0.7)


def test_paired_difference_closed_form() -> None:
    # differences 1, 2, 3: mean 2, sd 1, t(0.975, 2) = 4.3027
    c = paired_difference(np.array([2.0, 4.0, 6.0]), np.array([1.0, 2.0, 3.0]))
    assert c["mean_m"] == pytest.approx(2.0) and c["n_seeds"] == 3
    assert c["half_width_m"] == pytest.approx(4.3027 / np.sqrt(3.0), rel=1e-4)
    assert c["verdict"] == "n.s."
    assert paired_difference(np.array([1.0, 1.1, 0.9, 1.0]), np.zeros(4))["verdict"] == "worse"
    assert paired_difference(np.zeros(4), np.array([1.0, 1.1, 0.9, 1.0]))["verdict"] == "better"
    one = paired_difference(np.array([0.0]), np.array([1.0]))
    assert one["half_width_m"] is None and one["verdict"] == "n.s."
    # a seed with no figure (NaN) is left out of the pairs, not spread into the mean
    gap = paired_difference(np.array([1.0, np.nan, 1.2, 0.8]), np.zeros(4))
    assert gap["n_seeds"] == 3 and gap["mean_m"] == pytest.approx(1.0) and gap["verdict"] == "worse"
    assert paired_difference(np.array([np.nan]), np.array([1.0]))["mean_m"] is None


def test_paired_verdict_agrees_with_scipys_paired_t_test() -> None:
    """Two ways to the same decision: the interval excludes 0 exactly when ttest_rel's p < 0.05."""
    from scipy.stats import ttest_rel

    rng = np.random.default_rng(7)
    seen = set()
    for _ in range(300):
        n = int(rng.integers(2, 30))
        b = rng.uniform(1.0, 4.0, n)
        a = b + rng.normal(rng.normal(0.0, 0.3), rng.uniform(0.05, 1.0), n)
        c = paired_difference(a, b)
        p = ttest_rel(a, b).pvalue
        if abs(p - 0.05) < 1e-9:
            continue
        expect = "n.s." if p > 0.05 else ("worse" if a.mean() > b.mean() else "better")
        assert c["verdict"] == expect
        seen.add(expect)
    assert seen == {"n.s.", "worse", "better"}


@pytest.mark.parametrize("argv", [["run", "--seeds", "0"], ["run", "--fusion", "bogus"], ["run", "--jobs", "x"],
                                  ["bound"], ["report"]])
def test_bad_run_arguments_exit_2(argv, capsys) -> None:
    from slcp.deploy.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def test_report_of_a_directory_that_is_not_a_run(tmp_path, capsys) -> None:
    from slcp.deploy.cli import main

    assert main(["report", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err
    (tmp_path / "recorded").mkdir()
    (tmp_path / "recorded" / "messages.jsonl").write_text("")
    assert main(["report", str(tmp_path)]) == 2
    assert "cannot tell the scenario" in capsys.readouterr().err


def test_agent_config_rejects_an_unknown_fusion_rule(tmp_path) -> None:
    from slcp.deploy.processes import ConfigError, load_agent_config

    p = tmp_path / "a.toml"
    p.write_text('[agent]\nvehicle = "V1"\nscenario = "paper-1"\nfusion = "magic"\n')
    with pytest.raises(ConfigError, match="agent.fusion"):
        load_agent_config(p, None)
    p.write_text('[agent]\nvehicle = "V1"\nscenario = "paper-1"\nfusoin = "ci"\n')
    with pytest.raises(ConfigError, match="agent.fusoin: unknown field"):
        load_agent_config(p, None)
    p.write_text('[agent]\nvehicle = "V1"\nscenario = "paper-1"\nlane_constraint = "yes"\n')
    with pytest.raises(ConfigError, match="agent.lane_constraint: must be true or false"):
        load_agent_config(p, None)
    p.write_text('[agent]\nvehicle = "V1"\nscenario = "paper-1"\nlane_constraint = false\n')
    cfg, _ = load_agent_config(p, None)
    assert not cfg.settings.lane_constraint and cfg.lane_map is not None
    assert cfg.settings.separation_false_alarm == 1e-4
    for bad in ('"high"', "1.5", "-0.1", "true"):
        p.write_text(f'[agent]\nvehicle = "V1"\nscenario = "paper-1"\nintegrity_false_alarm = {bad}\n')
        with pytest.raises(ConfigError, match="agent.integrity_false_alarm: must be a probability"):
            load_agent_config(p, None)
    for value, expect in (("0", None), ("0.001", 0.001)):
        p.write_text(f'[agent]\nvehicle = "V1"\nscenario = "paper-1"\nintegrity_false_alarm = {value}\n')
        cfg, _ = load_agent_config(p, None)
        assert cfg.settings.separation_false_alarm == expect


@pytest.mark.timeout(120)
def test_bench_prints_every_figure(capsys) -> None:
    """The benchmark runs and reports each step cost (figures are printed, not asserted)."""
    import json

    from slcp.deploy.cli import main

    assert main(["bench", "--quick", "--json", "--drive", "/nonexistent"]) == 0
    out = json.loads(capsys.readouterr().out)
    for k in ("mechanisation_us", "imu_step_us", "covariance_step_us", "gnss_update_us", "range_update_split_ci_us",
              "stop_line_update_us", "beacon_encode_us", "beacon_decode_us"):
        assert out["steps"][k] > 0.0
    assert out["replay"] is None


def test_bench_prints_the_step_costs_beside_each_fleet_point(capsys, monkeypatch) -> None:
    """Each fleet point carries the agents' main step costs measured right after it (a stub
    stands for the fleet runs), in the JSON and on the point's own line."""
    import json

    from slcp.deploy import bench, fleet_bench
    from slcp.deploy.cli import main
    from slcp.deploy.commands.lab import FLEET_POINT_STEPS

    monkeypatch.setattr(fleet_bench, "run_fleet_point", lambda n, *a, **k: {"agents": n, "error": "stub"})
    calls = []  # the step costs themselves are the test above's: here, how often and where they go
    monkeypatch.setattr(bench, "micro_benchmarks", lambda quick=False: calls.append(quick) or {
        k: 1.0 + len(calls) for k in (*FLEET_POINT_STEPS, "imu_step_us")})
    assert main(["bench", "--quick", "--json", "--drive", "/nonexistent", "--fleet", "3,4"]) == 0
    points = json.loads(capsys.readouterr().out)["fleet"]
    assert [p["agents"] for p in points] == [3, 4]
    # once for the run, then once after each point, each point with its own
    assert calls == [True, True, True] and [p["steps"]["mechanisation_us"] for p in points] == [3.0, 4.0]
    assert all(set(p["steps"]) == set(FLEET_POINT_STEPS) for p in points)
    assert main(["bench", "--quick", "--drive", "/nonexistent", "--fleet", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = lines.index("  fleet   3 agents: stub")
    after = lines[at + 1]
    assert after.startswith("    step costs right after it: mechanisation ") and "beacon verify" in after


def _start_probe(*pid_files):
    """The pool probe with ``pid_files``, and its (first) worker's pid once that job started."""
    import subprocess
    import sys
    import time
    from pathlib import Path

    probe = subprocess.Popen([sys.executable, str(Path(__file__).with_name("_pool_probe.py")), *map(str, pid_files)],
                             cwd=Path(__file__).parents[1])
    deadline = time.monotonic() + 60
    while not (pid_files[0].exists() and pid_files[0].read_text()) and time.monotonic() < deadline:
        time.sleep(0.1)
    return probe, int(pid_files[0].read_text())


def _gone_within(pid: int, seconds: float) -> bool:
    """Whether process ``pid`` exits (or is a zombie waiting to be reaped) within ``seconds``."""
    import os
    import time
    from pathlib import Path

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return True
        except (ProcessLookupError, FileNotFoundError):
            return True
        time.sleep(0.1)
    return False


def _kill_and_expect_gone(study, workers: list[int]) -> None:
    """SIGKILL to the study process; each of its pool ``workers`` must exit within 10 s (one
    that does not is killed, and the test fails)."""
    import os
    import signal

    try:
        study.send_signal(signal.SIGKILL)
        study.wait(timeout=10)
        for w in workers:
            if not _gone_within(w, 10.0):
                os.kill(w, signal.SIGKILL)
                raise AssertionError("a pool worker outlived the killed study by 10 s")
    finally:
        if study.poll() is None:
            study.kill()
            study.wait(timeout=10)


@pytest.mark.fleet
def test_study_workers_stop_when_the_study_process_is_killed(tmp_path) -> None:
    """A study killed with SIGKILL must not leave its pool workers running its queued seeds."""
    probe, worker = _start_probe(tmp_path / "worker.pid")
    _kill_and_expect_gone(probe, [worker])


@pytest.mark.fleet
def test_an_in_process_study_killed_leaves_no_worker_running(tmp_path) -> None:
    """``slcp scenario study`` killed with SIGKILL: its pool workers (each running a seed of
    vehicle engines for a minute or more) stop too, instead of running on unseen on the cores."""
    import subprocess
    import sys
    import time

    study = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "scenario", "study", "paper-1", "--seeds",
                              "4", "--jobs", "1", "--out", str(tmp_path / "study")],
                             cwd=Path(__file__).parents[1], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while not workers and time.monotonic() < deadline and study.poll() is None:
            for d in Path("/proc").iterdir():
                try:
                    if (d.name.isdigit() and int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == study.pid
                            and b"multiprocessing.spawn" in (d / "cmdline").read_bytes()):
                        workers.append(int(d.name))
                except (OSError, ValueError, IndexError):
                    continue
            time.sleep(0.1)
    finally:
        if not workers:
            study.kill()
            study.wait(timeout=10)
    assert workers, "the study started no pool worker"
    _kill_and_expect_gone(study, workers)


@pytest.mark.fleet
@pytest.mark.slow
def test_an_interrupted_study_worker_does_not_start_the_seed_queued_behind(tmp_path) -> None:
    """SIGTERM to a pool worker during a seed: the seed's own cleanup runs (KeyboardInterrupt),
    then the worker exits instead of taking the call already queued to it."""
    import os
    import signal
    import time

    second = tmp_path / "second.pid"
    probe, worker = _start_probe(tmp_path / "first.pid", second)
    try:
        os.kill(worker, signal.SIGTERM)
        assert _gone_within(worker, 10.0), "the interrupted worker did not exit within 10 s"
        time.sleep(1.0)
        assert not second.exists(), "the interrupted worker started the next queued job"
    finally:
        probe.kill()
        probe.wait(timeout=10)


def test_the_stance_draws_are_the_truths_and_their_check_is_the_closed_form() -> None:
    """`stance_draws` gives the traffic model's draws without simulating it (two ways to the same
    numbers); `stance_check` is the mean z² of those draws against the χ² band of N draws."""
    from slcp.deploy.study import stance_check
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth, stance_draws

    scn = load_scenario("paper-2")
    seeds = [0, 9]
    for s in seeds:
        tr = build_truth(scn, stop_seed=s).traffic
        assert stance_draws(scn, s) == {v: (pytest.approx(tr.stop_gap[v]), tr.lateral[v]) for v in tr.lateral}
    check = stance_check(scn, seeds)
    v2 = next(v for v in scn.vehicles if v.id == "V2")
    z = np.array([[(stance_draws(scn, s)["V2"][k] - m) / sd for k, (m, sd) in enumerate((v2.stop_gap, v2.lateral))]
                  for s in seeds])
    c = check["V2"]
    assert c["lateral"]["mean_z2"] == pytest.approx(np.mean(z[:, 1] ** 2))
    assert c["both"]["mean_z2"] == pytest.approx(np.mean((z**2).sum(1)))
    assert c["stop_gap"]["band"] == list(anees_band(2, 1)) and c["both"]["band"] == list(anees_band(2, 2))
    assert c["lateral"]["inside"] == (anees_band(2, 1)[0] <= c["lateral"]["mean_z2"] <= anees_band(2, 1)[1])


def test_the_stance_check_of_many_seeds_sees_the_scenarios_sigma() -> None:
    """Over 400 seeds the draws are N(mean, σ²): every vehicle's mean z² is inside its band. And
    paper-2's seeds 0-24 did draw V2's lateral offsets too spread (mean z² 1.77, band
    0.52-1.63), which the report says."""
    from slcp.deploy.study import stance_check
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario("paper-2")
    many = stance_check(scn, list(range(400)))
    assert all(c[k]["inside"] for c in many.values() for k in ("stop_gap", "lateral", "both"))
    assert all(abs(c["both"]["mean_z2"] - 2.0) < 0.4 for c in many.values())
    st = {"seeds": list(range(25)), "rmse": {}, "anees": {}, "first_stopped": {},
          "stance_draws": stance_check(scn, list(range(25)))}
    assert st["stance_draws"]["V2"]["lateral"]["inside"] is False
    md = study_markdown(scn, st)
    assert "## The drivers' draws" in md and "| V2 | 0.89 | 1.77 (outside) | 2.66 |" in md


@pytest.mark.fleet
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_study_survives_a_seed_that_cannot_start(tmp_path) -> None:
    """Seed 1's emulator never publishes (no agent ever reports): the launcher gives it up after
    one resume at the same point, the study runs the seed once more, then aggregates seed 0
    alone, names seed 1 and why in study.json and the report, keeps each failed try's files
    apart from the study's runs, and leaves no process behind."""
    import json
    import subprocess

    import _study_seed

    from slcp.deploy.study import rebuild_study, run_study
    from slcp.hw_emulation.scenario import load_scenario

    out = tmp_path / "study"
    scn = str(short_scenario(tmp_path, "paper-1", 25.0))
    try:
        study = run_study(scn, [0, 1], ("SP",), out, jobs=2, runner=_study_seed.runner)
        assert study["seeds"] == [0]
        assert list(study["failed_seeds"]) == ["1"]
        assert "not restarted again" in study["failed_seeds"]["1"]
        assert (out / _study_seed.TRIES_FILE).read_text().split() == ["1", "1"]  # retried once
        assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["failed-seed-1-try1", "failed-seed-1-try2",
                                                                       "seed-0"]
        assert (out / "failed-seed-1-try2" / "logs" / "emulator.log").is_file()
        assert json.loads((out / "study.json").read_text())["failed_seeds"] == study["failed_seeds"]
        text = study_markdown(load_scenario(scn), study)
        assert "1 seed(s) failed and are left out" in text and "- seed 1: RuntimeError" in text
        assert rebuild_study(out)["failed_seeds"] == study["failed_seeds"]  # `slcp report` keeps them
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
        assert left == [], left
    finally:
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)


@pytest.mark.parametrize("strict, code", [(False, 0), (True, 1)])
def test_a_study_with_a_failed_seed_exits_non_zero_only_when_strict(strict, code, tmp_path, monkeypatch,
                                                                      capsys) -> None:
    import slcp.deploy.study as study_mod
    from slcp.deploy.cli import main

    def fake(scenario, seeds, methods, out, *a, **k):
        out.mkdir(parents=True)
        return {"seeds": seeds[:-1], "failed_seeds": {str(seeds[-1]): "RuntimeError: stalled"}}

    monkeypatch.setattr(study_mod, "run_study", fake)
    monkeypatch.setattr(study_mod, "study_markdown", lambda scn, study: "# report\n")
    argv = ["run", "paper-1", "--seeds", "3", "--out", str(tmp_path / "s")] + (["--strict"] if strict else [])
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "1 of 3 seeds failed" in err and "seeds 2" in err

    def none(*a, **k):
        raise study_mod.StudyError("no seed of the study finished: seed 0: RuntimeError: stalled")

    monkeypatch.setattr(study_mod, "run_study", none)
    argv[argv.index("--out") + 1] = str(tmp_path / "s2")  # the first study's folder is not reused
    assert main(argv) == 1
    assert "no seed of the study finished" in capsys.readouterr().err
