"""Write the real-drive results page (docs/results-real-drive.md) from a replay's own report.

    slcp replay rtklib ../shared/data/rtklibexplorer_drive_0708 --vehicle rtklibexplorer-drive \\
        --phases 6 --compare docs/data/rtklibexplorer-drive-authors-nhc.toml --out runs/real-drive
    python tools/real_drive_page.py runs/real-drive > docs/results-real-drive.md

The argument is the output folder of ``slcp replay`` (its ``report.md`` and ``metrics.json``).
The page is the report as the command wrote it, headings one level down, under a header that
gives the commands that remake it; nothing is typed in by hand.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from slcp.deploy.markdown_pages import PageError, demote, report_and_json, write_page

INTRO = """\
# Results on the real drive

!!! note "Generated"
    This page is the replay's own report, as these commands write it:

    ```bash
    {command}
    python tools/real_drive_page.py {run_dir} > docs/results-real-drive.md
    ```

The drive is rtklibexplorer's `drive_0708`: a car with a roof-mounted u-blox RTK receiver and a
consumer MEMS IMU, nine minutes of residential streets and a parking lot (its `DATASET.md` in
`../shared/data/rtklibexplorer_drive_0708/`). The replay runs the engine a vehicle runs
([architecture](architecture.md)) with the car's [profile](vehicle-profiles.md): the drive becomes
the messages its sensor drivers would publish. There is no independent ground truth; GNSS
outages are simulated by withholding the receiver's RTK-fixed solutions, and the estimates that
coast through them are scored against the withheld fixes at the antenna. The filter is causal:
no smoothing and no look-ahead.

The figures beside ours were measured once by running the data authors' own filter on the same
drive and protocol (`docs/data/rtklibexplorer-drive-authors-nhc.toml` says how); ours are measured
again by the command above. What the figures show, what holds them back and what was tried:
[Analysis of the real drive](real-drive-analysis.md). How to replay another recording:
[Recording formats](recording-formats.md).
"""


def replay_report(run_dir: Path) -> tuple[str, str]:
    """The command that wrote the replay in ``run_dir``, and its report (markdown)."""
    text, m = report_and_json(run_dir, "metrics.json", "replay", "metrics")
    try:
        float(m["outage_h_rms_m"])
    except (ValueError, KeyError, TypeError) as exc:
        raise PageError(f"{run_dir / 'metrics.json'}: not a replay's metrics ({exc!r})") from exc
    commands = [line.strip("`") for line in text.splitlines() if line.startswith("`slcp replay ")]
    if len(commands) != 1:
        raise PageError(f"{run_dir / 'report.md'}: not a replay's report (no `slcp replay ...` line)")
    return commands[0], text


def build_page(run_dir: Path) -> str:
    """The page: the header with the commands, then the replay's report."""
    command, report = replay_report(run_dir)
    return INTRO.format(command=command, run_dir=f"runs/{run_dir.name}") + "\n" + demote(report)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="the output folder of slcp replay (--out)")
    args = ap.parse_args(argv)
    return write_page(lambda: build_page(args.run_dir), "real_drive_page")


if __name__ == "__main__":
    raise SystemExit(main())
