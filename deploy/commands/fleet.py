"""The fleet's processes: ``slcp agent``, ``emulate``, ``router``, ``sensors``, ``record`` and ``keys``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import cli_types as T


def add_agent(sub) -> None:
    """The ``agent`` command's parser."""
    ag = sub.add_parser("agent", help="run one vehicle agent (Zenoh)")
    ag.add_argument("--vehicle", help="vehicle id (overrides the config file)")
    ag.add_argument("--config", type=Path, required=True, help="agent TOML (docs/cli.md, agent configuration)")
    ag.add_argument("--nice", type=T.int_range(0, 19), default=0, metavar="0-19",
                    help="lower this process's scheduling priority by N (default 0)")
    ag.add_argument("--stand-in", action="store_true",
                    help="for benchmarks: once the engine has sent its first beacon and estimate, estimate "
                         "nothing and send their copies at the engine's rates (what the rest of a fleet costs)")


def add_emulate(sub) -> None:
    """The ``emulate`` command's parser."""
    em = sub.add_parser("emulate", help="run the emulator service (sensors, UWB, V2V radio) over Zenoh")
    em.add_argument("scenario", help="shipped scenario name or .toml")
    em.add_argument("--seed", type=T.seed, default=0, help="run seed: sensor noise and where drivers stop (default 0)")
    em.add_argument(
        "--speed", type=T.positive_float, default=None, help="real-time factor (default: as fast as agents keep up)"
    )
    em.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    em.add_argument("--listen", action="append", type=T.listen_endpoint, default=[], help="Zenoh endpoint to listen on")
    em.add_argument("--mode", choices=("peer", "client"), default="peer",
                    help="Zenoh mode (default peer; client: through the router given by --connect only)")
    em.add_argument("--faults", type=Path, default=None, help="fault schedule (TOML, docs/security.md)")
    em.add_argument(
        "--wait-agents",
        type=T.nonnegative_float,
        default=20.0,
        help="wait up to this long for every vehicle's agent before starting [s] (default 20; 0: start at once)",
    )
    em.add_argument("--start-at", type=T.nonnegative_float, default=None, metavar="T",
                    help="resume the scenario at sensor time T [s] (a restarted emulator)")
    em.add_argument("--fleet", type=Path, default=None,
                    help="fleet directory: connect with mutual TLS as identity 'emulator' (tls/ endpoints)")


def add_router(sub) -> None:
    """The ``router`` command's parser."""
    ro = sub.add_parser("router", help="run the infrastructure Zenoh router (TLS + ACL with --fleet)")
    ro.add_argument("--listen", action="append", type=T.listen_endpoint, default=[],
                    help="endpoint (repeatable; default tls/127.0.0.1:7447 with --fleet, else tcp/127.0.0.1:7447)")
    ro.add_argument(
        "--fleet",
        type=Path,
        default=None,
        help="fleet directory (slcp keys create): mutual TLS and an ACL in which a vehicle publishes only "
        "under its own keys",
    )
    ro.add_argument(
        "--print-config", action="store_true", help="print the router's Zenoh configuration (JSON5) and exit"
    )


def add_sensors(sub) -> None:
    """The ``sensors`` command's parser."""
    se = sub.add_parser(
        "sensors", help="publish a vehicle's real GNSS (NMEA/UBX) and IMU from serial ports or log files"
    )
    se.add_argument("--vehicle", required=True, help="vehicle id of the sensor topics")
    se.add_argument("--gnss", default=None, metavar="nmea|ubx:PATH[@BAUD]",
                    help="GNSS receiver: a serial device (e.g. nmea:/dev/ttyACM0@115200) or a log file")
    se.add_argument(
        "--imu", default=None, metavar="csv:PATH[@BAUD]", help="IMU text lines: a serial device or a log file"
    )
    se.add_argument("--imu-units", default="m/s2,rad/s", metavar="ACCEL,GYRO",
                    help="units of the IMU lines: m/s2|g|mg and rad/s|deg/s|mrad/s (default m/s2,rad/s)")
    se.add_argument("--profile", default=None, metavar="PROFILE",
                    help="the vehicle's profile (a TOML file or a shipped profile's name): its IMU mount and "
                         "time-offset prior")
    se.add_argument("--imu-mount", default=None, metavar="ROLL,PITCH,YAW",
                    help="sensor-to-body rotation [deg] (default: the profile's, else 0,0,0: the IMU axes are "
                         "forward, right, down)")
    se.add_argument("--imu-time-offset", type=T.finite_float, default=None,
                    help="added to the IMU time stamps [s] (default: the profile's prior, else 0)")
    se.add_argument(
        "--uere", type=T.positive_float, default=2.5, help="NMEA without GST: horizontal sigma = HDOP x UERE [m]"
    )
    se.add_argument(
        "--speed", type=T.positive_float, default=1.0, help="pacing of log files (real-time factor, default 1)"
    )
    se.add_argument("--wait-agent", type=T.nonnegative_float, default=30.0, metavar="S",
                    help="log files start once the vehicle's agent subscribes to them, waiting at most S "
                         "seconds (default 30; 0: at once). Serial devices never wait")
    se.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    se.add_argument("--listen", action="append", type=T.listen_endpoint, default=[], help="Zenoh endpoint to listen on")
    se.add_argument("--fleet", type=Path, default=None,
                    help="fleet directory: mutual TLS to the router as the vehicle (its .key/.crt)")


def add_record(sub) -> None:
    """The ``record`` command's parser."""
    rc = sub.add_parser("record", help="record every estimate and diagnostics message (JSON lines, appending)")
    rc.add_argument("--out", type=Path, required=True, help="recording file (appended to; a restart continues it)")
    rc.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    rc.add_argument("--fleet", type=Path, default=None, help="fleet directory: mutual TLS as identity 'recorder'")
    rc.add_argument("--bag", type=Path, default=None,
                    help="also write a ROS 2 bag in MCAP storage to this new directory (standard ROS 2 "
                         "message types; the map frame's origin is the first estimate's position)")
    rc.add_argument("--bag-inputs", action="store_true",
                    help="the bag also holds the vehicles' inputs: IMU samples, GNSS fixes, UWB rounds and beacons")


def add_view(sub) -> None:
    """The ``view`` command's parser."""
    vw = sub.add_parser("view", help="show a running fleet live: a map in the browser, and Foxglove")
    vw.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    vw.add_argument("--fleet", type=Path, default=None, help="fleet directory: mutual TLS as identity 'recorder'")
    vw.add_argument("--scenario", default=None,
                    help="draw this scenario's lanes and stop lines (shipped name or TOML file; default: no site)")
    vw.add_argument("--port", type=T.port, default=8780,
                    help="port of the map page, http://127.0.0.1:PORT/ (default 8780; 0: any free port)")
    vw.add_argument("--foxglove", type=T.port, default=None, metavar="PORT",
                    help="also serve Foxglove's WebSocket protocol on ws://127.0.0.1:PORT (default: not)")


def add_keys(sub) -> None:
    """The ``keys`` command's parser."""
    ky = sub.add_parser("keys", help="create or list a fleet's CA, vehicle keys and certificates")
    ksub = ky.add_subparsers(dest="keys_command", required=True)
    kc = ksub.add_parser(
        "create", help="create a fleet CA (if absent) and a key + certificate per vehicle and the router"
    )
    kc.add_argument("dir", type=Path, help="fleet directory (ca.crt, <vehicle>.crt/.key, router.crt/.key)")
    kc.add_argument("vehicles", nargs="+", help="vehicle ids")
    kc.add_argument("--router-host", action="append", default=None,
                    help="host name or address in the router certificate (repeatable; default 127.0.0.1, localhost)")
    kc.add_argument("--days", type=T.positive_int, default=365, help="certificate validity [days] (default 365)")
    kc.add_argument("--force", action="store_true",
                    help="re-issue the listed vehicles' keys and certificates with the existing CA")
    kc.add_argument("--new-ca", action="store_true",
                    help="replace the fleet CA, and with it every key and certificate of the directory's fleet")
    kc.add_argument("--infra", action="append", default=None,
                    help="infrastructure identity (repeatable; default: emulator, recorder)")
    kl = ksub.add_parser("list", help="check a fleet directory and list its certificates and key ids")
    kl.add_argument("dir", type=Path)


def _cmd_agent(args: argparse.Namespace) -> int:
    import asyncio

    from ..processes import agent_main

    return asyncio.run(agent_main(args.config, args.vehicle, args.nice, args.stand_in))


def _cmd_emulate(args: argparse.Namespace) -> int:
    import asyncio

    from slcp.transport.zenoh_bus import ZenohConfig

    from ..processes import emulator_main

    z = ZenohConfig(mode=args.mode, connect=tuple(args.connect), listen=tuple(args.listen))
    if args.fleet:
        from ..zenoh_security import client_config

        z = client_config(args.fleet, "emulator", tuple(args.connect))
    return asyncio.run(emulator_main(args.scenario, args.seed, args.speed, z, faults_path=args.faults,
                                     start_at=args.start_at, wait_for_agents=args.wait_agents))


def _cmd_sensors(args: argparse.Namespace) -> int:
    import asyncio
    import math

    from slcp.transport.zenoh_bus import ZenohConfig
    from slcp.vehicles.profile import VehicleProfile

    from ..sensors.driver import SourceSpec, sensors_main
    from ..sensors.imu import ImuAdapter, parse_units
    from ..vehicle_files import load_vehicle

    profile = load_vehicle(args.profile) if args.profile else VehicleProfile()
    mount: tuple[float, ...] = profile.imu.mount_rpy
    if args.imu_mount is not None:
        try:
            mount = tuple(math.radians(float(x)) for x in args.imu_mount.split(","))
        except ValueError:
            mount = ()
        if len(mount) != 3 or not all(math.isfinite(x) for x in mount):
            raise ValueError(f"--imu-mount {args.imu_mount!r}: expected ROLL,PITCH,YAW in degrees")
    offset = profile.time.imu_offset_s if args.imu_time_offset is None else args.imu_time_offset
    units = parse_units(args.imu_units)
    if not (args.speed > 0 and args.uere > 0):
        raise ValueError("--speed and --uere must be > 0")
    gnss = SourceSpec.parse("gnss", args.gnss) if args.gnss else None
    imu = SourceSpec.parse("imu", args.imu) if args.imu else None
    if gnss is None and imu is None:
        raise ValueError("nothing to read: give --gnss and/or --imu")
    adapter = ImuAdapter(args.vehicle, mount, offset)
    z = ZenohConfig(connect=tuple(args.connect), listen=tuple(args.listen))
    if args.fleet:
        from ..zenoh_security import client_config

        z = client_config(args.fleet, args.vehicle, tuple(args.connect))
    counters = asyncio.run(sensors_main(z, args.vehicle, gnss, imu, adapter, units, args.uere, args.speed,
                                        args.wait_agent))
    print(json.dumps(counters))
    return 0


def _cmd_infrastructure(args: argparse.Namespace) -> int:
    import asyncio

    from slcp.transport.zenoh_bus import ZenohConfig

    from ..processes import recorder_main, router_main

    if args.command in ("record", "view"):
        z = ZenohConfig(mode="client" if args.fleet else "peer", connect=tuple(args.connect))
        if args.fleet:
            from ..zenoh_security import client_config

            z = client_config(args.fleet, "recorder", tuple(args.connect))
        if args.command == "view":
            return asyncio.run(recorder_main(z, None, view_port=args.port, foxglove_port=args.foxglove,
                                             scenario=args.scenario))
        if args.bag is not None and args.bag.exists():
            raise ValueError(f"--bag {args.bag}: exists; a bag is written to a new directory")
        if args.bag_inputs and args.bag is None:
            raise ValueError("--bag-inputs: give the bag's directory with --bag")
        return asyncio.run(recorder_main(z, args.out, args.bag, bag_inputs=args.bag_inputs))
    if args.fleet:
        from ..zenoh_security import as_json5, router_config

        z = router_config(args.fleet, tuple(args.listen) or ("tls/127.0.0.1:7447",))
        if args.print_config:
            print(as_json5(z), end="")
            return 0
    else:
        z = ZenohConfig(mode="router", listen=tuple(args.listen) or ("tcp/127.0.0.1:7447",))
        if args.print_config:
            from ..zenoh_security import as_json5

            print(as_json5(z), end="")
            return 0
    return asyncio.run(router_main(z))


def _cmd_keys(args: argparse.Namespace) -> int:
    from slcp.transport.security import TrustStore, create_fleet

    if args.keys_command == "create":
        hosts = tuple(args.router_host) if args.router_host else ("127.0.0.1", "localhost")
        infra = tuple(args.infra) if args.infra else ("emulator", "recorder")
        written = create_fleet(args.dir, args.vehicles, hosts, args.days, overwrite=args.force, infrastructure=infra,
                               new_ca=args.new_ca)
        for p in written:
            print(f"wrote {p}")
        if not written:
            print(f"{args.dir}: every certificate exists already (use --force to replace)")
    store = TrustStore.from_dir(args.dir)
    print(f"{args.dir}: fleet CA {store.ca.subject.rfc4514_string()}, valid to {store.ca.not_valid_after_utc:%Y-%m-%d}")
    kids = store.key_ids()
    for name, role in sorted(store.roles.items(), key=lambda kv: (kv[1] != "vehicle", kv[0])):
        print(f"  {name:16s} {role:15s}" + (f" beacon key id {kids[name].hex()}" if name in kids else ""))
    return 0


HANDLERS = {
    "agent": _cmd_agent,
    "emulate": _cmd_emulate,
    "router": _cmd_infrastructure,
    "sensors": _cmd_sensors,
    "record": _cmd_infrastructure,
    "view": _cmd_infrastructure,
    "keys": _cmd_keys,
}
