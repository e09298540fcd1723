"""The configuration and file-format reference page, made from the dataclasses that the files
fill (``docs/reference-config.md``).

``python -m slcp.deploy.config_reference > docs/reference-config.md`` regenerates it; the test suite
fails when the committed page and the dataclasses disagree, or a field has no description.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import sys

HEADER = """# Configuration and file-format reference

The fields of the TOML tables that slcp reads, generated from the dataclasses they fill
(`python -m slcp.deploy.config_reference > docs/reference-config.md`). Values are in SI units and
radians unless a field says otherwise. [Scenario format](scenario-format.md), [Command
line](cli.md) (agent configuration), [Vehicle profiles](vehicle-profiles.md) and [Security,
faults and misbehaviour](security.md) (fault schedules) explain them with examples.
"""


def _tables():
    from slcp.agent.nav.measurements.stop_line import StopGapModel
    from slcp.hw_emulation.faults import Fault
    from slcp.hw_emulation.sensors.camera import LaneCameraModel
    from slcp.hw_emulation.sensors.gnss import GnssModel
    from slcp.hw_emulation.sensors.imu import ImuModel
    from slcp.hw_emulation.sensors.radio import RadioModel
    from slcp.hw_emulation.sensors.uwb import UwbModel
    from slcp.transport.zenoh_bus import ZenohConfig
    from slcp.vehicles.profile import ConstraintSpec, GnssSpec, ImuSpec, InitialSpec, TimeSpec

    from .agent_configs import FilterOptions

    return [
        ("Vehicle profile", "[imu] (datasheet units)", ImuSpec),
        ("Vehicle profile", "[time]", TimeSpec),
        ("Vehicle profile", "[gnss]", GnssSpec),
        ("Vehicle profile", "[constraints]", ConstraintSpec),
        ("Vehicle profile", "[initial]", InitialSpec),
        ("Scenario file", "[sensors.imu]; a vehicle's imu = {...}; an agent configuration's [imu]", ImuModel),
        ("Scenario file", "[sensors.gnss]; a vehicle's gnss = {...}", GnssModel),
        ("Scenario file", "[sensors.camera]", LaneCameraModel),
        ("Scenario file", "[uwb]; an agent configuration's [uwb]", UwbModel),
        ("Scenario file", "[radio]", RadioModel),
        ("Agent configuration", "[filter]", FilterOptions),
        ("Agent configuration", "[stop_gap] (a field left out keeps the scenario's, without one 1.5, 0.3, 1.75, 0.3, "
         "2.5 m in this order)", StopGapModel),
        ("Agent configuration", "[zenoh] (with tls = true/false besides)", ZenohConfig),
        ("Fault schedule", "[[fault]]", Fault),
    ]


def field_docs(cls) -> dict[str, str]:
    """Each field's description: from the ``Attributes``/``Parameters`` section of the class
    docstring (``name[, name2] : type`` then indented text), else from ``#:`` comments above it."""
    out: dict[str, str] = {}
    doc = inspect.getdoc(cls) or ""
    m = re.search(r"^(Attributes|Parameters)\n-+\n(.*?)(?:\n\n[A-Z][a-z]+\n-+\n|\Z)", doc, re.S | re.M)
    if m:
        names: list[str] = []
        for line in m.group(2).splitlines():
            head = re.match(r"^(\w+(?:\s*,\s*\w+)*)\s*:", line)
            if head and not line.startswith(" "):
                names = [n.strip() for n in head.group(1).split(",")]
                for n in names:
                    out.setdefault(n, "")
            elif line.strip() and names:
                for n in names:
                    out[n] = (out[n] + " " + line.strip()).strip()
    src = inspect.getsource(cls).splitlines()
    pending: list[str] = []
    for line in src:
        s = line.strip()
        if s.startswith("#:"):
            pending.append(s[2:].strip())
            continue
        fm = re.match(r"^(\w+)\s*:[^=]*(?:=.*?)?(?:#:\s*(.*))?$", s)
        if fm and fm.group(1) in {f.name for f in dataclasses.fields(cls)}:
            text = " ".join(pending + ([fm.group(2)] if fm.group(2) else []))
            if text and not out.get(fm.group(1)):
                out[fm.group(1)] = text
        pending = []
    return out


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        v = f.default
    elif f.default_factory is not dataclasses.MISSING:
        v = f.default_factory()
    else:
        return "required"
    if isinstance(v, float):
        return f"`{v:.6g}`"
    return f"`{v!r}`"


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def config_reference_markdown() -> str:
    out = [HEADER]
    section = None
    for title, where, cls in _tables():
        if title != section:
            out += [f"## {title}", ""]
            section = title
        summary = (inspect.getdoc(cls) or "").split("\n\n")[0]
        out += [f"### `{where}`", "", f"{_cell(summary)} (`{cls.__module__}.{cls.__qualname__}`)", "",
                "| field | type | default | description |", "|---|---|---|---|"]
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            if f.name.startswith("_"):
                continue
            typ = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
            out.append(f"| `{f.name}` | `{_cell(typ)}` | {_default(f)} | {_cell(docs.get(f.name, ''))} |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def main() -> int:
    sys.stdout.write(config_reference_markdown())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
