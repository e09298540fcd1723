"""Write the fleet results page (docs/results-fleet.md) from the studies' own reports.

    python tools/fleet_results_page.py runs/paper-1-25 runs/paper-2-25 runs/rush-hour-25 > docs/results-fleet.md

Each argument is the output folder of a seeded study: ``slcp run SCENARIO --seeds N`` (a fleet
of agent processes over Zenoh per seed) or ``slcp scenario study SCENARIO --seeds N`` (the same
vehicle engines in process). The page is their ``report.md`` files as the commands wrote them,
headings one level down, under a header that gives the commands that remake it; nothing is
typed in by hand, so the page says what the code does today and nothing else.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from slcp.agent.methods import DEFAULT_FUSION
from slcp.deploy.markdown_pages import PageError, demote, report_and_json, write_page

INTRO = """\
# Fleet results

!!! note "Generated"
    This page is the studies' own reports, as these commands write them (`slcp run --seeds`: each
    seed a fleet of agent processes over Zenoh, with signed beacons; `slcp scenario study`: the
    same vehicle engines in process, for a fleet too large to run as processes seed after seed
    on one machine):

    ```bash
{commands}
    python tools/fleet_results_page.py {dirs} > docs/results-fleet.md
    ```

What the figures mean: the methods and the paper's rows are in [Algorithms](algorithms.md), the
bound beside each cell (the joint posterior Cramér-Rao bound of the scenario's truth) in
[The physical limit](algorithms.md#the-physical-limit-slcp-bound), and what is known to hold the figures
back in [Known limits](known-limits.md). The study's windows are the scenario's own (t_s1–t_e:
from the first vehicle's stop to the end; *standing*: the times each vehicle truly stands).
"""


def study_command(study_dir: Path) -> tuple[str, str]:
    """The command that wrote the study in ``study_dir``, and its report (markdown)."""
    text, study = report_and_json(study_dir, "study.json", "study", "summary")
    meta = study_dir / "study.json"
    try:
        seeds = [int(s) for s in study["seeds"]]
        scenario = str(study["scenario"])
    except (ValueError, KeyError, TypeError) as exc:
        raise PageError(f"{meta}: not a study's summary ({exc!r})") from exc
    if not seeds:
        raise PageError(f"{meta}: no seeds")
    name = study_dir.name
    if "summary" in study:  # slcp scenario study (in process): seeds 0..N-1
        bound = any(isinstance(s, dict) and "bound" in s for s in study.get("per_seed", []))
        cmd = f"slcp scenario study {scenario} --seeds {len(seeds)}{' --bound' if bound else ''} --out runs/{name}"
    else:
        cmd = f"slcp run {scenario} --seeds {len(seeds)}"
        if seeds[0] != 0:
            cmd += f" --seed {seeds[0]}"
        if study.get("fusion", DEFAULT_FUSION) != DEFAULT_FUSION:
            cmd += f" --fusion {study['fusion']}"
        if study.get("lane_constraint") is False:
            cmd += " --no-lane-constraint"
        cmd += f" --out runs/{name}"
    return cmd, text


def build_page(study_dirs: list[Path]) -> str:
    """The page: the header with the commands, then each study's report."""
    if not study_dirs:
        raise PageError("no study folders given")
    parts = [study_command(d) for d in study_dirs]
    commands = "\n".join(f"    {cmd}" for cmd, _ in parts)
    dirs = " ".join(f"runs/{d.name}" for d in study_dirs)
    page = [INTRO.format(commands=commands, dirs=dirs)]
    page += [demote(report) for _, report in parts]
    return "\n".join(page)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("studies", nargs="+", type=Path,
                    help="study output folders (slcp run --seeds, slcp scenario study)")
    args = ap.parse_args(argv)
    return write_page(lambda: build_page(args.studies), "fleet_results_page")


if __name__ == "__main__":
    raise SystemExit(main())
