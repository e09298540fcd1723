"""Where a run or a study writes: folders named after the scenario, never hidden, and never
written over by accident (a second run into a folder would append to its recording)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path


class RunDirError(ValueError):
    """An output folder that cannot be used; the message names it and says what to do."""


def folder_stem(scenario_name: str) -> str:
    """A folder name for a scenario: its name with anything but letters, digits, ``.``, ``_``
    and ``-`` replaced, and no leading dot (a hidden folder)."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", scenario_name).lstrip("._-")
    return stem or "scenario"


def next_free(root: Path, stem: str) -> Path:
    """``root/stem``, or ``root/stem-2``, ``-3``, ... : the first that does not exist yet."""
    path, k = root / stem, 1
    while path.exists():
        k += 1
        path = root / f"{stem}-{k}"
    return path


def looks_like_a_run(path: Path) -> bool:
    """Whether ``path`` holds a previous slcp run or study (what ``--force`` may replace): a
    run's recording or start record, or a study's summary beside its seed folders."""
    return ((path / "recorded" / "messages.jsonl").is_file() or (path / "recorded" / "bag").is_dir()
            or (path / "config" / "run.json").is_file()
            or ((path / "study.json").is_file() and any(path.glob("seed-*"))))


def _too_wide(path: Path) -> bool:
    """The working folder, the home folder or a folder above either: never removed whole."""
    p = path.resolve()
    return any(p == q or p in q.parents for q in (Path.cwd().resolve(), Path.home().resolve()))


def prepare_out(path: Path, force: bool) -> None:
    """Check an output folder the user named: new, or empty, or with ``force`` a previous run's
    (removed first, so that nothing of it mixes with the new run). Anything else is refused."""
    if not path.exists():
        return
    if not path.is_dir():
        raise RunDirError(f"{path}: exists and is not a folder")
    if not any(path.iterdir()):
        return
    if not force:
        raise RunDirError(f"{path}: exists and is not empty; choose another --out, or add --force to replace "
                          "the run in it")
    if not looks_like_a_run(path) or _too_wide(path):
        raise RunDirError(f"{path}: not a slcp run folder (no recorded/messages.jsonl, config/run.json, or study.json "
                          "beside seed-* folders), or the working or home folder; --force replaces only runs")
    shutil.rmtree(path)
