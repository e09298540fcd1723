"""The command-line reference page, made from the parsers themselves (``docs/reference-cli.md``).

``python -m slcp.deploy.cli_reference > docs/reference-cli.md`` regenerates it; the test suite fails
when the committed page and the parsers disagree, or when an option has no help text.
"""

from __future__ import annotations

import argparse
import sys

HEADER = """# Command-line reference

Every `slcp` command and option, generated from the parsers
(`python -m slcp.deploy.cli_reference > docs/reference-cli.md`); [Command line](cli.md) explains
them with examples.
"""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _flags(action: argparse.Action) -> str:
    names = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.dest}`"
    if action.nargs == 0:
        return names
    if action.metavar is not None:
        meta = action.metavar if isinstance(action.metavar, str) else " ".join(action.metavar)
    elif action.choices is not None:
        meta = "{" + ",".join(str(c) for c in action.choices) + "}"
    else:
        meta = action.dest.upper()
    return f"{names} `{meta}`"


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, [], argparse.SUPPRESS) or action.required:
        return ""
    return f"`{action.default}`"


def _section(parser: argparse.ArgumentParser, path: str, summary: str, out: list[str]) -> None:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    rows = [a for a in parser._actions
            if not isinstance(a, (argparse._SubParsersAction, argparse._HelpAction, argparse._VersionAction))]
    if rows or not subs:
        out += [f"## `{path}`", ""]
        if summary:
            out += [_cell(summary) + ".", ""]
        usage = " ".join(parser.format_usage().split())
        out += ["```", usage.removeprefix("usage: "), "```", ""]
        out += ["| argument | default | what it does |", "|---|---|---|"]
        for a in rows:
            out.append(f"| {_flags(a)} | {_default(a)} | {_cell(a.help or '')} |")
        out.append("")
    for sp in subs:
        helps = {c.dest: c.help for c in sp._choices_actions}
        for name, sub in sp.choices.items():
            _section(sub, f"{path} {name}", helps.get(name, ""), out)


def cli_reference_markdown(parser: argparse.ArgumentParser) -> str:
    """The reference page of ``parser`` and its sub-commands, in Markdown."""
    out = [HEADER]
    _section(parser, parser.prog, "", out)
    return "\n".join(out).rstrip() + "\n"


def main() -> int:
    from .cli import build_parser

    sys.stdout.write(cli_reference_markdown(build_parser()))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
