"""The command line refuses what it cannot do right: one clear line and a non-zero exit for a
wrong option, a bad endpoint or a bad file; run folders that are neither hidden nor written
over; a version; a shipped scenario to start from; and an interrupted run that says what it
stopped and reports what it recorded."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slcp.deploy import cli_types
from slcp.deploy.cli import build_parser, main
from slcp.deploy.run_dirs import RunDirError, folder_stem, next_free, prepare_out

from conftest import short_scenario

CLI = [sys.executable, "-m", "slcp.deploy.cli"]


def _refused(argv: list[str], capsys) -> str:
    """Run the CLI on ``argv`` expecting argparse to refuse it; return its one-line message."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return err[-1]


@pytest.mark.parametrize(("argv", "says"), [
    (["run", "--speed", "-1"], "above 0"),
    (["run", "--speed", "0"], "above 0"),
    (["run", "--speed", "nan"], "finite"),
    (["run", "--speed", "fast"], "expected a number"),
    (["run", "--seed", "-3"], "seed of 0 or more"),
    (["run", "--seeds", "0"], "positive integer"),
    (["run", "--jobs", "1.5"], "positive integer"),
    (["emulate", "paper-1", "--wait-agents", "-1"], "0 or more"),
    (["emulate", "paper-1", "--start-at", "-2"], "0 or more"),
    (["replay", "rtklib", "x", "--imu-time-offset", "inf"], "finite"),
    (["replay", "rtklib", "x", "--first-outage", "-1"], "0 or more"),
    (["replay", "rtklib", "x", "--publish", "--duration", "0"], "above 0"),
    (["sensors", "--vehicle", "V0", "--uere", "-2"], "above 0"),
    (["scenario", "sp-check", "paper-1", "--seeds", "0"], "positive integer"),
    (["bench", "--fleet-duration", "-5"], "above 0"),
    (["run", "--agent-nice", "50"], "expected an integer from 0 to 19, got '50'"),
    (["agent", "--nice", "-1"], "expected an integer from 0 to 19, got '-1'"),
    (["bench", "--fleet-imu-batch", "0"], "expected an integer from 1 to 100, got '0'"),
    (["bound", "paper-1", "--plot", "/nonexistent/dir/x.png"], "its folder /nonexistent/dir does not exist"),
    (["scenario", "show", "paper-1", "--plot", "x.txt"], "expected a file name ending in .png"),
    (["replay", "rtklib", "x", "--outage", "-5:30"], "must be positive"),  # not "expected one argument"
])
def test_a_wrong_number_is_one_line_and_exit_2(argv, says, capsys) -> None:
    line = _refused(argv, capsys)
    assert says in line and line.startswith("slcp ") and "error: argument" in line


def test_a_value_starting_with_a_minus_and_a_digit_is_a_value() -> None:
    """argparse takes a token starting with '-' for an option unless it is a plain number: a
    negative mount angle first in a list was refused ("expected one argument")."""
    args = build_parser().parse_args(["sensors", "--vehicle", "V0", "--imu-mount", "-1.5,0,90",
                                      "--imu-time-offset", "-.125"])
    assert args.imu_mount == "-1.5,0,90" and args.imu_time_offset == -0.125
    with pytest.raises(SystemExit):  # an option that is no option is still refused
        build_parser().parse_args(["sensors", "--vehicle", "V0", "--imu-mount", "--bogus"])


@pytest.mark.parametrize("bad", ["127.0.0.1:7447", "tcp/127.0.0.1", "tcp/127.0.0.1:70000",
                                 "carrier-pigeon/127.0.0.1:7447", "tcp/:7447", "tcp/[::1:7447", ""])
def test_a_malformed_endpoint_is_refused_before_zenoh_sees_it(bad, capsys) -> None:
    for argv in (["record", "--out", "x.jsonl", "--connect", bad], ["router", "--listen", bad]):
        line = _refused(argv, capsys)
        assert "endpoint" in line or "port" in line or "protocol" in line or "brackets" in line, line


def test_well_formed_endpoints_pass_as_given(capsys) -> None:
    for ok in ("tcp/127.0.0.1:7447", "tls/localhost:7447", "udp/127.0.0.1:1", "tcp/[::1]:7447",
               "tcp/[fe80::1%eth0]:7447", "unixsock-stream//tmp/zenoh.sock", "tcp/127.0.0.1:7447#iface=lo",
               "serial//dev/ttyUSB0#baudrate=115200", "vsock/VMADDR_CID_ANY:7447"):
        assert cli_types.endpoint(ok) == ok
    # port 0 (any free port) is for listening only
    assert cli_types.listen_endpoint("tcp/127.0.0.1:0") == "tcp/127.0.0.1:0"
    assert "port from 1" in _refused(["record", "--out", "x.jsonl", "--connect", "tcp/127.0.0.1:0"], capsys)


def test_every_option_has_help_text() -> None:
    """Every option of every command says what it does (the CLI reference is made from these)."""
    import argparse

    missing = []

    def walk(parser: argparse.ArgumentParser, path: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{path} {name}")
            elif action.option_strings and not action.help:
                missing.append(f"{path} {'/'.join(action.option_strings)}")

    walk(build_parser(), "slcp")
    assert missing == []


def test_the_cli_reference_page_is_the_parsers(monkeypatch) -> None:
    """docs/reference-cli.md is what the parsers generate (regenerate it with the command in its
    header after changing an option)."""
    from slcp.deploy.cli_reference import cli_reference_markdown

    monkeypatch.setenv("COLUMNS", "100")
    page = Path(__file__).resolve().parents[1] / "docs" / "reference-cli.md"
    assert page.read_text() == cli_reference_markdown(build_parser()), \
        "docs/reference-cli.md is out of date: python -m slcp.deploy.cli_reference > docs/reference-cli.md"


def test_the_config_reference_page_is_the_dataclasses() -> None:
    """docs/reference-config.md is what the dataclasses generate, and every field is described."""
    import dataclasses

    from slcp.deploy.config_reference import _tables, config_reference_markdown, field_docs

    for _, _, cls in _tables():
        undocumented = [f.name for f in dataclasses.fields(cls) if not f.name.startswith("_")
                        and not field_docs(cls).get(f.name)]
        assert undocumented == [], f"{cls.__name__}: {undocumented} have no description"
    page = Path(__file__).resolve().parents[1] / "docs" / "reference-config.md"
    assert page.read_text() == config_reference_markdown(), \
        "docs/reference-config.md is out of date: python -m slcp.deploy.config_reference > docs/reference-config.md"


def test_version(capsys) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"slcp {version('slcp')}"


def test_a_shipped_scenario_exports_to_a_file_that_runs_as_it(tmp_path, capsys) -> None:
    from slcp.hw_emulation.scenario import load_scenario

    assert main(["scenario", "export", "paper-1"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("#") and 'name = "paper-1"' in text
    out = tmp_path / "mine.toml"
    assert main(["scenario", "export", "paper-1", "--out", str(out)]) == 0
    assert f"slcp run {out}" in capsys.readouterr().out
    assert out.read_text() == text and load_scenario(out).name == "paper-1"
    out.write_text("# my edits\n")
    assert main(["scenario", "export", "paper-1", "--out", str(out)]) == 2  # kept
    assert "exists" in capsys.readouterr().err and out.read_text() == "# my edits\n"
    assert main(["scenario", "export", "paper-1", "--out", str(out), "--force"]) == 0
    assert out.read_text() == text
    assert main(["scenario", "export", "nope"]) == 2
    assert "unknown scenario 'nope'" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["scenario", "faults", "agent"])
def test_a_file_of_garbage_bytes_is_an_error_that_names_it(what, tmp_path, capsys) -> None:
    bad = tmp_path / f"garbage-{what}.toml"
    bad.write_bytes(bytes(range(128, 256)) * 4)
    argv = {"scenario": ["scenario", "show", str(bad)],
            "faults": ["run", "paper-1", "--faults", str(bad), "--out", str(tmp_path / "run")],
            "agent": ["agent", "--config", str(bad)]}[what]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("slcp: error: ") and str(bad) in err and "UTF-8" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("body, field", [
    ('[zenoh]\nmulticast_scouting = "false"\n', "zenoh.multicast_scouting: must be true or false"),
    ("[zenoh]\nlease_ms = 1e14\n", "zenoh.lease_ms: must be an integer from 100 to 3600000"),
    ("[zenoh]\nlease_ms = 100000000000000\n", "zenoh.lease_ms: must be an integer from 100 to 3600000"),
    ("[zenoh]\nconfig_file = 5\n", "zenoh.config_file: must be the path of a Zenoh JSON5 file"),
    ('[zenoh]\nconnect = ["tcp/nohost"]\n', "zenoh.connect: expected HOST:PORT"),
    ('[zenoh]\nlisten = ["carrier-pigeon/1.2.3.4:5"]\n', "zenoh.listen: unknown protocol"),
    ("[agent]\nscenario = 5\n", "agent.scenario: must be a scenario name or file"),
])
def test_every_agent_config_value_is_type_checked(body, field, tmp_path, capsys) -> None:
    """#39 finding 10: a wrong value is one line naming the file and the field, not a traceback
    (nor a string "false" read as true)."""
    cfg = tmp_path / "agent.toml"
    head = '[agent]\nvehicle = "V0"\n' if not body.startswith("[agent]") else '[agent]\nvehicle = "V0"\n' + body[8:]
    cfg.write_text(head if body.startswith("[agent]") else head + body)
    assert main(["agent", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"slcp: error: {cfg}: {field}"), err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


@pytest.mark.parametrize("text, field", [("agent = 0\n", "agent: must be a table"),
                                         ('imu = 3\n[agent]\nvehicle = "V0"\n', "imu: must be a table")])
def test_an_agent_file_section_that_is_not_a_table_is_named(text, field, tmp_path, capsys) -> None:
    cfg = tmp_path / "agent.toml"
    cfg.write_text(text)
    assert main(["agent", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"slcp: error: {cfg}: {field}") and "Traceback" not in err, err


def test_run_folders_are_named_after_the_scenario_never_hidden_never_reused(tmp_path) -> None:
    assert folder_stem("paper-1") == "paper-1"
    assert folder_stem("../mine/my 4cars") == "mine_my_4cars"
    assert folder_stem(".hidden") == "hidden" and folder_stem("..") == "scenario"
    assert next_free(tmp_path, "paper-1-seed0") == tmp_path / "paper-1-seed0"
    (tmp_path / "paper-1-seed0").mkdir()
    (tmp_path / "paper-1-seed0-2").mkdir()
    assert next_free(tmp_path, "paper-1-seed0") == tmp_path / "paper-1-seed0-3"


def test_an_explicit_out_folder_is_replaced_only_with_force_and_only_if_it_is_a_run(tmp_path, monkeypatch) -> None:
    prepare_out(tmp_path / "new", force=False)  # a new folder: fine
    empty = tmp_path / "empty"
    empty.mkdir()
    prepare_out(empty, force=False)
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "thesis.tex").write_text("precious")
    with pytest.raises(RunDirError, match="not empty"):
        prepare_out(notes, force=False)
    with pytest.raises(RunDirError, match="not a slcp run folder"):
        prepare_out(notes, force=True)
    assert (notes / "thesis.tex").read_text() == "precious"
    (notes / "metrics.json").write_text("{}")  # another tool's file of that name does not make a run
    with pytest.raises(RunDirError, match="not a slcp run folder"):
        prepare_out(notes, force=True)
    run = tmp_path / "run"
    (run / "config").mkdir(parents=True)
    (run / "config" / "run.json").write_text("{}")
    (run / "recorded").mkdir()
    with pytest.raises(RunDirError, match="--force"):
        prepare_out(run, force=False)
    prepare_out(run, force=True)
    assert not run.exists()
    monkeypatch.chdir(run.parent)  # the working folder itself is never removed whole
    (tmp_path / "recorded").mkdir()
    (tmp_path / "recorded" / "messages.jsonl").write_text("")
    with pytest.raises(RunDirError, match="working or home folder"):
        prepare_out(tmp_path, force=True)
    afile = tmp_path / "file"
    afile.write_text("x")
    with pytest.raises(RunDirError, match="not a folder"):
        prepare_out(afile, force=True)


def test_slcp_run_refuses_a_used_out_folder_before_starting_anything(tmp_path, capsys) -> None:
    used = tmp_path / "used"
    used.mkdir()
    (used / "report.md").write_text("an earlier run's")
    assert main(["run", "paper-1", "--out", str(used)]) == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in used.iterdir()) == ["report.md"]


@pytest.mark.fleet
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_ctrl_c_stops_the_fleet_says_so_and_reports_what_was_recorded(tmp_path) -> None:
    """SIGINT to `slcp run` once the fleet has recorded a few seconds: exit 130, one line saying
    the processes are stopped and up to which sensor time it recorded, a report of that partial
    recording, and no process left behind."""
    out = tmp_path / "run"
    scn = short_scenario(tmp_path, "paper-1", 25.0)
    # played at 1x: agent-paced, the 25 s can play in seconds and end between two looks below.
    # SIGINT as a terminal leaves it: a suite started in the background of a non-interactive
    # shell ignores SIGINT, and its children would inherit that
    p = subprocess.Popen([*CLI, "run", str(scn), "--seed", "3", "--speed", "1", "--out", str(out)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        rec = out / "recorded" / "messages.jsonl"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.2)
            if rec.exists() and rec.stat().st_size > 200_000:
                break
        assert rec.exists(), "nothing recorded"
        os.kill(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
        # no process left behind, looked for before the clean-up below
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)
    assert left == [], left
    assert p.returncode == 130, err[-2000:]
    assert "interrupted; the fleet's processes are stopped" in err
    assert "recorded to t=" in err and "report.md" in err and "Traceback" not in err
    m = json.loads((out / "metrics.json").read_text())
    assert m["seed"] == 3  # the run's own seed, from config/run.json, not the scenario's draw
    assert (out / "report.md").is_file()


@pytest.mark.fleet
@pytest.mark.slow
def test_record_from_an_endpoint_nobody_listens_on_says_so_and_retries(tmp_path) -> None:
    """`slcp record --connect` to a port where no router listens: one line saying it cannot reach
    it and keeps trying (it does not hang silently); Ctrl-C then ends it cleanly."""
    from conftest import free_port

    port = free_port()
    log = tmp_path / "stderr.txt"
    with log.open("w") as fh:
        p = subprocess.Popen([*CLI, "record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path / "r.jsonl")],
                             stdout=subprocess.DEVNULL, stderr=fh, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "cannot reach" not in log.read_text():
            time.sleep(0.2)
        os.kill(p.pid, signal.SIGINT)
        p.wait(timeout=30)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    err = log.read_text()
    lines = [x for x in err.splitlines() if x.strip()]
    assert any(f"cannot reach tcp/127.0.0.1:{port}" in x and "retrying" in x for x in lines), err
    assert "Traceback" not in err and ".rs" not in err
    assert p.returncode in (0, 130)



@pytest.mark.fleet
def test_a_client_whose_router_is_not_there_is_one_clean_error(tmp_path, capsys) -> None:
    """A Zenoh client (an agent or the recorder of a deployed fleet) cannot start without its
    router: the error names the endpoint and carries no Rust source path."""
    import asyncio

    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    from conftest import free_port

    ep = f"tcp/127.0.0.1:{free_port()}"

    async def open_client() -> None:
        ZenohBus(ZenohConfig(mode="client", connect=(ep,)))

    with pytest.raises(ConnectionError) as exc:
        asyncio.run(open_client())
    text = str(exc.value)
    assert ep in text and "client" in text and ".rs" not in text
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f'[agent]\nvehicle = "V0"\nscenario = "paper-1"\n\n[zenoh]\nmode = "client"\nconnect = ["{ep}"]\n')
    assert main(["agent", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slcp: error: cannot open a Zenoh session") and ep in err[0]


def test_the_docs_site_builds_strictly(tmp_path) -> None:
    """`mkdocs build --strict`: every page in the navigation, no broken link or anchor."""
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-f", str(repo / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert (tmp_path / "site" / "index.html").is_file() and (tmp_path / "site" / "cli" / "index.html").is_file()


def test_the_readme_is_a_front_page() -> None:
    """At most 200 lines, no dates or commit hashes, and every link in it resolves."""
    import re

    repo = Path(__file__).resolve().parents[1]
    text = (repo / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), "a date in the README"
    assert not re.search(r"\b[0-9a-f]{7,40}\b", text), "a commit hash in the README"
    for target in re.findall(r"\]\(([^)#]+)", text):
        if "://" not in target:
            assert (repo / target).exists(), target


def test_the_terminal_summary_is_a_compact_plain_table_that_flags_nees(tmp_path) -> None:
    from slcp.deploy.summary import NEES_BAND, terminal_summary
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario("paper-1")

    def cell(rmse, nees):
        return {"rmse_m": rmse, "along_rmse_m": rmse, "cross_rmse_m": rmse, "nees_h": nees, "bound_rms_m": 0.1}

    metrics = {"seed": 4, "rmse": {"t_s1-t_e": {
        "V1": {"SP": cell(4.05, 1.2), "SL-SP": cell(0.15, 1.5), "CP": cell(3.35, 0.8), "SL-CP": cell(0.15, 9.0)},
        "V2": {"SP": cell(3.6, 0.01), "SL-SP": cell(3.4, 1.2), "CP": cell(2.5, 0.7), "SL-CP": cell(0.06, 0.2)}}},
        "first_stopped": {"V1": {"SL-SP": {"precision": 1.0, "recall": 0.98}}}}
    text = terminal_summary(scn, metrics, tmp_path / "report.md")
    print(text)
    assert "<br>" not in text and "|" not in text and max(len(x) for x in text.splitlines()) < 120
    v1 = next(x for x in text.splitlines() if x.strip().startswith("V1"))
    v2 = next(x for x in text.splitlines() if x.strip().startswith("V2"))
    assert "0.15 [0.25] !" in v1 and "4.05 [5.18]" in v1 and "4.05 [5.18] !" not in v1  # 9.0 > band
    assert "3.60 [4.91] !" in v2 and "0.06 [3.84]" in v2 and "0.06 [3.84] !" not in v2  # 0.01 < band
    assert NEES_BAND[0] < 0.2 < 7.0 < NEES_BAND[1]
    assert "V1 SL-SP precision 1.000, recall 0.980" in text and str(tmp_path / "report.md") in text
