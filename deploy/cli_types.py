"""Argument types of the ``slcp`` command line: each turns a bad value into one clear line from
argparse (``slcp run: error: argument --speed: ...``, exit 2) instead of a run that goes wrong."""

from __future__ import annotations

import argparse
import math
import re

#: Zenoh's endpoint protocols (link types)
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
#: protocols whose address is not HOST:PORT
_PATH_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")
_ENDPOINT = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>[^#?]+)(?P<rest>[#?].*)?$")


class Parser(argparse.ArgumentParser):
    """argparse's parser, but a token that starts with a minus and a digit is always a value:
    argparse takes only plain negative numbers for values, so ``--imu-mount -1.5,0,90`` or
    ``--outage -5:30`` said "expected one argument". No slcp option starts with a digit, and
    the subcommands' parsers are of this class too."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def finite_float(text: str) -> float:
    """Any finite number (e.g. a time offset, which may be negative)."""
    return _number(text)


def positive_float(text: str) -> float:
    """A finite number above zero (a real-time factor, a duration, a σ)."""
    v = _number(text)
    if v <= 0.0:
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}")
    return v


def nonnegative_float(text: str) -> float:
    """A finite number of zero or more (a start time, a margin)."""
    v = _number(text)
    if v < 0.0:
        raise argparse.ArgumentTypeError(f"expected a number of 0 or more, got {text!r}")
    return v


def _integer(text: str, what: str, low: int) -> int:
    try:
        v = int(text)
    except ValueError:
        v = None
    if v is None or v < low:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return v


def int_range(low: int, high: int):
    """An argument type: an integer from ``low`` to ``high``, named as such in its error (argparse's
    ``choices=range(...)`` lists every allowed value)."""

    def parse(text: str) -> int:
        v = _integer(text, f"an integer from {low} to {high}", low)
        if v > high:
            raise argparse.ArgumentTypeError(f"expected an integer from {low} to {high}, got {text!r}")
        return v

    parse.__name__ = f"integer {low}-{high}"
    return parse


#: the file types a plot may be written as (by its suffix)
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def plot_file(text: str):
    """A plot to write: a file name with a suffix of :data:`PLOT_SUFFIXES`, in a folder that exists
    (checked before the work whose result it draws)."""
    from pathlib import Path

    p = Path(text)
    if p.suffix.lower() not in PLOT_SUFFIXES:
        raise argparse.ArgumentTypeError(f"expected a file name ending in {', '.join(PLOT_SUFFIXES)}, got {text!r}")
    if not p.parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: its folder {p.parent} does not exist")
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: a folder, not a file")
    return p


def positive_int(text: str) -> int:
    """An integer of 1 or more (a count)."""
    return _integer(text, "a positive integer", 1)


def seed(text: str) -> int:
    """A random seed: an integer of 0 or more (numpy refuses negative seeds)."""
    return _integer(text, "a seed of 0 or more (an integer)", 0)


def port(text: str) -> int:
    """A TCP port to listen on: 0 (any free one) to 65535."""
    v = _integer(text, "a port number from 0 to 65535", 0)
    if v > 65535:
        raise argparse.ArgumentTypeError(f"expected a port number from 0 to 65535, got {text!r}")
    return v


def listen_endpoint(text: str) -> str:
    """An endpoint to listen on: as :func:`endpoint`, and port 0 (any free port) is allowed."""
    return _endpoint(text, listen=True)


def endpoint(text: str) -> str:
    """A Zenoh endpoint ``PROTOCOL/HOST:PORT`` (``unixsock-stream/PATH``, ...) to connect to,
    checked before Zenoh sees it: Zenoh's own error for a malformed one is a Rust backtrace."""
    return _endpoint(text, listen=False)


def _endpoint(text: str, listen: bool) -> str:
    m = _ENDPOINT.match(text.strip())
    if m is None:
        raise argparse.ArgumentTypeError(f"expected a Zenoh endpoint PROTOCOL/HOST:PORT (e.g. tcp/127.0.0.1:7447), "
                                         f"got {text!r}")
    proto, addr = m["proto"], m["addr"]
    if proto not in ENDPOINT_PROTOCOLS:
        raise argparse.ArgumentTypeError(f"unknown protocol {proto!r} in {text!r} "
                                         f"(one of {', '.join(ENDPOINT_PROTOCOLS)})")
    if proto in _PATH_PROTOCOLS:
        return text.strip()
    host, sep, port = addr.rpartition(":")
    low = 0 if listen else 1
    if not sep or not host or not port.isdigit() or not low <= int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port from {low} to 65535 after {proto}/, "
                                         f"got {text!r}")
    if host.startswith("[") != host.endswith("]"):
        raise argparse.ArgumentTypeError(f"unbalanced brackets around the IPv6 address in {text!r}")
    return text.strip()
