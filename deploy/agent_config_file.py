"""An agent's configuration file (TOML), read and checked: :func:`load_agent_config` gives the
engine's configuration and the Zenoh configuration, or a :class:`ConfigError` naming the file
and field. The full description is in docs/cli.md; in short::

    [agent]
    vehicle = "V1"                              # may also be given with --vehicle
    scenario = "paper-1"                        # site map and sensor characteristics
    site = "maps/junction.osm"                  # optional: the site from a Lanelet2 map (docs/site-maps.md)
    profile = "my-car.toml"                     # optional vehicle profile (IMU, antenna, constraints;
                                                # docs/vehicle-profiles.md), relative to this file;
                                                # it replaces the [imu] and [filter] sections
    methods = ["SP", "SL-SP", "CP", "SL-CP"]
    fusion = "source-ci"                        # paper | source-ci | split-ci | ci (how CP methods fuse ranges)
    lane_constraint = true                      # SL methods also keep to the map's lanes (false: stop line only)
    integrity_false_alarm = 1e-4                # CP/SL-CP tested against SP/SL-SP (solution separation,
                                                # agent.integrity): false-alarm probability per test; 0: off

    [imu] [gnss] [uwb] [stop_gap] [filter]      # optional: the sensors' and the stop gap's models
                                                # (docs/cli.md), in place of a scenario's

    [security]                                  # optional; without it beacons are neither signed nor checked
    trust_dir = "keys"                          # ca.crt + vehicle certificates (``slcp keys create``);
                                                # relative paths are relative to this file
    key = "keys/V1.key"                         # this vehicle's private key (default <trust_dir>/<vehicle>.key)
    sign_beacons = true                         # false: the keys serve zenoh.tls only; beacons are
                                                # neither signed nor checked

    [zenoh]
    mode = "peer"                               # peer | client | router
    connect = ["tcp/127.0.0.1:7447"]
    listen = []
    lease_ms = 2000
    autoconnect_strategy = "greater-zid"        # greater-zid | always: how peers dial the peers they learn of
    config_file = ""                            # optional Zenoh JSON5 (TLS, ACL)
    tls = false                                 # true: mutual TLS to the fleet router (`slcp router`) with
                                                # this vehicle's certificate from [security]; connect must
                                                # be tls/<host>:<port> and the mode is client
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tomllib
from pathlib import Path

from slcp.transport.zenoh_bus import AUTOCONNECT_STRATEGIES, ZenohConfig

from .cli_types import endpoint, listen_endpoint

#: the longest liveliness lease a configuration may ask for [ms]
MAX_LEASE_MS = 3_600_000


class ConfigError(ValueError):
    """A process configuration file is invalid (the message names the field)."""


def zenoh_config(d: dict, source: str) -> ZenohConfig:
    allowed = {"mode", "connect", "listen", "lease_ms", "autoconnect_strategy", "config_file", "multicast_scouting"}
    for k in d:
        if k not in allowed:
            raise ConfigError(f"{source}: zenoh.{k}: unknown field (known: {', '.join(sorted(allowed))})")
    mode = d.get("mode", "peer")
    if mode not in ("peer", "client", "router"):
        raise ConfigError(f"{source}: zenoh.mode: must be peer, client or router, got {mode!r}")
    for k in ("connect", "listen"):
        v = d.get(k, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise ConfigError(f"{source}: zenoh.{k}: must be a list of endpoint strings")
        for x in v:
            try:
                (listen_endpoint if k == "listen" else endpoint)(x)
            except argparse.ArgumentTypeError as exc:
                raise ConfigError(f"{source}: zenoh.{k}: {exc}") from None
    lease = d.get("lease_ms", 2000)
    if isinstance(lease, bool) or not isinstance(lease, int) or not 100 <= lease <= MAX_LEASE_MS:
        raise ConfigError(f"{source}: zenoh.lease_ms: must be an integer from 100 to {MAX_LEASE_MS} (an hour), "
                          f"got {lease!r}")
    if not isinstance(d.get("multicast_scouting", False), bool):
        raise ConfigError(f"{source}: zenoh.multicast_scouting: must be true or false, "
                          f"got {d['multicast_scouting']!r}")
    cf = d.get("config_file", "")
    if not isinstance(cf, str):
        raise ConfigError(f"{source}: zenoh.config_file: must be the path of a Zenoh JSON5 file, got {cf!r}")
    strategy = d.get("autoconnect_strategy", "greater-zid")
    if strategy not in AUTOCONNECT_STRATEGIES:
        raise ConfigError(f"{source}: zenoh.autoconnect_strategy: must be one of "
                          f"{', '.join(AUTOCONNECT_STRATEGIES)}, got {strategy!r}")
    return ZenohConfig(mode=mode, connect=tuple(d.get("connect", [])), listen=tuple(d.get("listen", [])),
                       lease_ms=lease, autoconnect_strategy=strategy, config_file=cf or None,
                       multicast_scouting=d.get("multicast_scouting", False))


def load_agent_config(path: Path, vehicle: str | None):
    """The agent configuration and Zenoh configuration of an agent's TOML file; ``vehicle``
    overrides its ``agent.vehicle``. :class:`ConfigError` names the file and field."""
    data = _read_toml(Path(path), "an agent configuration")
    unknown = set(data) - {"agent", "imu", "gnss", "uwb", "stop_gap", "filter", "security", "zenoh"}
    if unknown:
        raise ConfigError(f"{path}: [{sorted(unknown)[0]}]: unknown section "
                          "(known: agent, imu, gnss, uwb, stop_gap, filter, security, zenoh)")
    for name, section in data.items():
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: {name}: must be a table ([{name}]), got {section!r}")
    a = _agent_section(data.get("agent", {}), path, vehicle)
    cfg = _filter_config(a, data, path)
    sec = {}
    if "security" in data:
        sec = security_config(data["security"], Path(path), a["vehicle"])
        cfg = dataclasses.replace(cfg, signer=sec["signer"], trust=sec["trust"])
    return cfg, _agent_zenoh(dict(data.get("zenoh", {})), sec, path, a["vehicle"])


def _read_toml(path: Path, what: str) -> dict:
    try:
        return tomllib.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not {what} (not UTF-8 text)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from exc


def _agent_section(a: dict, path: Path, vehicle: str | None) -> dict:
    """The ``[agent]`` section, checked, with its defaults."""
    from slcp.agent.methods import DEFAULT_FUSION, FUSION_RULES, METHODS, MethodSpec

    vid = vehicle or a.get("vehicle")
    if not isinstance(vid, str) or not vid:
        raise ConfigError(f"{path}: agent.vehicle: missing (or give --vehicle)")
    methods = a.get("methods", list(METHODS))
    if not isinstance(methods, list):
        raise ConfigError(f"{path}: agent.methods: must be a list")
    for m in methods:
        try:
            MethodSpec.of(m)
        except ValueError as exc:
            raise ConfigError(f"{path}: agent.methods: {exc}") from None
    fusion = a.get("fusion", DEFAULT_FUSION)
    if fusion not in FUSION_RULES:
        raise ConfigError(f"{path}: agent.fusion: must be one of {', '.join(FUSION_RULES)}, got {fusion!r}")
    lane = a.get("lane_constraint", True)
    if not isinstance(lane, bool):
        raise ConfigError(f"{path}: agent.lane_constraint: must be true or false")
    integrity = a.get("integrity_false_alarm", None)
    if integrity is not None and (isinstance(integrity, bool) or not isinstance(integrity, (int, float))
                                  or not 0.0 <= integrity < 1.0):
        raise ConfigError(f"{path}: agent.integrity_false_alarm: must be a probability in [0, 1) "
                          f"(0 switches the test off), got {integrity!r}")
    unknown = set(a) - {"vehicle", "scenario", "site", "site_origin", "profile", "methods", "fusion",
                        "lane_constraint", "integrity_false_alarm"}
    if unknown:
        raise ConfigError(f"{path}: agent.{sorted(unknown)[0]}: unknown field")
    scenario = a.get("scenario")
    if scenario is not None and (not isinstance(scenario, str) or not scenario):
        raise ConfigError(f"{path}: agent.scenario: must be a scenario name or file, got {scenario!r}")
    profile = a.get("profile")
    if profile is not None and (not isinstance(profile, str) or not profile):
        raise ConfigError(f"{path}: agent.profile: must be the path of a vehicle profile, got {profile!r}")
    return {"vehicle": vid, "methods": tuple(methods), "fusion": fusion, "lane_constraint": lane,
            "integrity_false_alarm": integrity, "scenario": a.get("scenario"),
            "profile": None if profile is None else Path(path).parent / profile, **_site_fields(a, path)}


def _site_fields(a: dict, path: Path) -> dict:
    """``agent.site`` (a Lanelet2 map, relative to the file) and ``agent.site_origin`` (latitude,
    longitude [deg], height [m]; default: the map's map_projector_info.yaml), checked."""
    site, origin = a.get("site"), a.get("site_origin")
    if site is not None and (not isinstance(site, str) or not site):
        raise ConfigError(f"{path}: agent.site: must be the path of a Lanelet2 map (.osm), got {site!r}")
    if origin is not None:
        if site is None:
            raise ConfigError(f"{path}: agent.site_origin: only with agent.site")
        if (not isinstance(origin, list) or len(origin) != 3
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in origin)
                or not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 180)):
            raise ConfigError(f"{path}: agent.site_origin: must be [latitude, longitude] in degrees and a height "
                              f"in metres, got {origin!r}")
        origin = (math.radians(origin[0]), math.radians(origin[1]), float(origin[2]))
    return {"site": None if site is None else Path(path).parent / site, "site_origin": origin}


def _filter_config(a: dict, data: dict, path: Path):
    """The engine's configuration: the site's (a scenario) or none, then the ``[imu]`` and
    ``[gnss]`` sections and the integrity setting."""
    from slcp.agent.nav.measurements.stop_line import StopGapModel
    from slcp.hw_emulation.scenario import load_scenario, model_from_table
    from slcp.hw_emulation.sensors.imu import ImuModel
    from slcp.hw_emulation.sensors.uwb import UwbModel
    from slcp.vehicles.profile import load_profile

    from .agent_configs import (
        FilterOptions,
        agent_config,
        siteless_agent_config,
        with_filter,
        with_gnss,
        with_imu,
        with_profile,
        with_site,
        with_uwb,
    )

    vid, methods, fusion = a["vehicle"], a["methods"], a["fusion"]
    if a["profile"] is not None and ("imu" in data or "filter" in data):
        raise ConfigError(f"{path}: [{'imu' if 'imu' in data else 'filter'}]: not with agent.profile "
                          "(the profile describes the IMU and the installation)")
    try:
        if a["scenario"] is not None:
            cfg = agent_config(load_scenario(a["scenario"]), vid, methods, fusion, a["lane_constraint"])
        else:
            cfg = siteless_agent_config(vid, methods, fusion)
            cfg = dataclasses.replace(cfg, settings=dataclasses.replace(cfg.settings,
                                                                        lane_constraint=a["lane_constraint"]))
        if a["site"] is not None:
            from slcp.geo.lanelet2_site import read_lanelet2

            cfg = with_site(cfg, read_lanelet2(a["site"], a["site_origin"]))
        if a["profile"] is not None:
            cfg = with_profile(cfg, load_profile(a["profile"]))
        if "imu" in data:
            cfg = with_imu(cfg, model_from_table(ImuModel, data["imu"], str(path), "imu"))
        if "gnss" in data:
            cfg = with_gnss(cfg, _gnss_table(data["gnss"], path))
        if "uwb" in data:
            cfg = with_uwb(cfg, model_from_table(UwbModel, data["uwb"], str(path), "uwb"))
        if "stop_gap" in data:
            cfg = dataclasses.replace(cfg, gap=model_from_table(StopGapModel, data["stop_gap"], str(path), "stop_gap",
                                                                cfg.gap))
        if "filter" in data:
            cfg = with_filter(cfg, model_from_table(FilterOptions, data["filter"], str(path), "filter"))
    except ValueError as exc:  # ScenarioError included
        raise ConfigError(str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    integrity = a["integrity_false_alarm"]
    if integrity is not None:
        cfg = dataclasses.replace(cfg, settings=dataclasses.replace(
            cfg.settings, separation_false_alarm=float(integrity) if integrity > 0 else None))
    return cfg


def _agent_zenoh(z: dict, sec: dict, path: Path, vid: str):
    """The ``[zenoh]`` section; with ``tls``, the fleet's mutual-TLS client configuration."""
    tls = z.pop("tls", False)
    if not isinstance(tls, bool):
        raise ConfigError(f"{path}: zenoh.tls: must be true or false")
    if not tls:
        return zenoh_config(z, str(path))
    if not sec:
        raise ConfigError(f"{path}: zenoh.tls: needs a [security] section (the fleet directory and key)")
    from .zenoh_security import client_config

    zc = zenoh_config(z, str(path))
    try:
        return client_config(sec["trust_dir"], vid, zc.connect, zc.lease_ms)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: zenoh.tls: {exc}") from None


def _gnss_table(d, path: Path) -> dict:
    """The ``[gnss]`` section: the filter's GNSS error model (SI units)."""
    from .agent_configs import GNSS_FIELDS

    if not isinstance(d, dict):
        raise ConfigError(f"{path}: [gnss]: must be a table")
    out = {}
    for k, v in d.items():
        if k not in GNSS_FIELDS:
            raise ConfigError(f"{path}: gnss.{k}: unknown field (known: {', '.join(sorted(GNSS_FIELDS))})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or v == float("inf"):
            raise ConfigError(f"{path}: gnss.{k}: must be a finite number >= 0, got {v!r}")
        if (k.endswith("tau") or k == "reset_after") and v <= 0:
            raise ConfigError(f"{path}: gnss.{k}: must be > 0, got {v!r}")
        if k == "gate" and v >= 1:
            raise ConfigError(f"{path}: gnss.gate: a χ² probability below 1 (0: no gate), got {v!r}")
        out[k] = float(v)
    return out


def security_config(d: dict, path: Path, vehicle: str) -> dict:
    """The signer and trust store of a ``[security]`` section (paths relative to the file)."""
    from slcp.transport.security import BeaconSigner, SecurityError, TrustStore

    if not isinstance(d, dict):
        raise ConfigError(f"{path}: [security]: must be a table")
    unknown = set(d) - {"trust_dir", "key", "sign_beacons"}
    if unknown:
        raise ConfigError(f"{path}: security.{sorted(unknown)[0]}: unknown field (known: key, sign_beacons, trust_dir)")
    sign = d.get("sign_beacons", True)
    if not isinstance(sign, bool):
        raise ConfigError(f"{path}: security.sign_beacons: must be true or false, got {sign!r}")
    for k in ("trust_dir", "key"):
        if k in d and (not isinstance(d[k], str) or not d[k]):
            raise ConfigError(f"{path}: security.{k}: must be a non-empty path string")
    if "trust_dir" not in d:
        raise ConfigError(f"{path}: security.trust_dir: missing")
    trust_dir = path.parent / d["trust_dir"]
    if not sign:
        return {"signer": None, "trust": None, "trust_dir": trust_dir}
    key = path.parent / d["key"] if "key" in d else trust_dir / f"{vehicle}.key"
    try:
        trust = TrustStore.from_dir(trust_dir)
        signer = BeaconSigner.from_file(vehicle, key)
    except SecurityError as exc:
        raise ConfigError(f"{path}: security: {exc}") from None
    if vehicle not in trust.vehicles():
        own = trust_dir / f"{vehicle}.crt"
        why = f" ({own}: {trust.refused[own]})" if own in trust.refused else ""
        raise ConfigError(f"{path}: security: no valid vehicle certificate for {vehicle} in {trust_dir}{why}")
    return {"signer": signer, "trust": trust, "trust_dir": trust_dir}


#: environment variable with the pid of the launcher that started this process (`slcp run`)
