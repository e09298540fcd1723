"""Zenoh settings for a deployed fleet: mutual TLS with the fleet's certificates and the router's
access control list (ACL), built from a fleet directory (``slcp keys create``).

Every process connects to the infrastructure router (``slcp router``) in client mode over
``tls/...`` and presents its certificate; the router admits only certificates of the fleet CA and
identifies each connection by the certificate's common name (CN). The ACL (``default_permission:
deny``) then allows:

* a **vehicle** ``V`` (OU=vehicle) to publish only under its own keys: ``radio/tx/V``,
  ``estimate/V/*``, ``diag/V``, ``diag/V.sensors``, ``sensor/V/*`` and ``uwb/V`` (its own sensor
  drivers, ``slcp sensors``); to declare its liveliness tokens ``alive/agent/V`` and
  ``alive/sensors/V`` only; to subscribe to its own inputs (``sensor/V/*``,
  ``uwb/V``, ``radio/rx/V``) and to liveliness under ``alive/**``; and to be sent only those;
* **infrastructure** (OU=infrastructure: the emulator, the recorder) everything under ``slcp/v1``.

No zenoh import here: the dictionaries go into :class:`transport.zenoh_bus.ZenohConfig` (``extra``)
or, as JSON5, into a Zenoh configuration file for ``zenohd`` or another client.
"""

from __future__ import annotations

import json
from pathlib import Path

from slcp.transport import keys
from slcp.transport.security import INFRASTRUCTURE, VEHICLE, TrustStore
from slcp.transport.zenoh_bus import ZenohConfig

_R = keys.ROOT


def tls_settings(fleet_dir: Path, identity: str, listen: bool = False, verify_name: bool = True) -> dict:
    """``transport/link/tls`` for ``identity`` (its ``<identity>.key``/``.crt`` in the fleet
    directory), mutual TLS, the fleet CA as the only root."""
    d = Path(fleet_dir).resolve()
    for f in ("ca.crt", f"{identity}.crt", f"{identity}.key"):
        if not (d / f).is_file():
            raise FileNotFoundError(f"{d / f}: missing (create it with `slcp keys create {d} ...`)")
    out = {"root_ca_certificate": str(d / "ca.crt"), "enable_mtls": True,
           "connect_private_key": str(d / f"{identity}.key"), "connect_certificate": str(d / f"{identity}.crt"),
           "verify_name_on_connect": verify_name}
    if listen:
        out.update(listen_private_key=str(d / f"{identity}.key"), listen_certificate=str(d / f"{identity}.crt"))
    return out


def _vehicle_rules(v: str) -> list[dict]:
    return [
        {"id": f"{v}-publish", "permission": "allow", "flows": ["ingress"], "messages": ["put", "delete"],
         "key_exprs": [keys.radio_tx(v), f"{_R}/estimate/{v}/*", keys.diag(v), keys.diag(f"{v}.sensors"),
                       f"{_R}/sensor/{v}/*", keys.uwb(v)]},
        {"id": f"{v}-subscribe", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_subscriber"],
         "key_exprs": [f"{_R}/sensor/{v}/*", keys.uwb(v), keys.radio_rx(v)]},
        {"id": f"{v}-liveliness", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_liveliness_subscriber", "liveliness_query"], "key_exprs": [f"{_R}/alive/**"]},
        {"id": f"{v}-token", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
         "key_exprs": [keys.alive("agent", v), keys.alive("sensors", v)]},
        {"id": f"{v}-deliver", "permission": "allow", "flows": ["egress"], "messages": ["put", "delete"],
         "key_exprs": [f"{_R}/sensor/{v}/*", keys.uwb(v), keys.radio_rx(v)]},
        {"id": f"{v}-learn", "permission": "allow", "flows": ["egress"],
         "messages": ["declare_subscriber", "liveliness_token", "reply"], "key_exprs": [f"{_R}/**"]},
    ]


def access_control(store: TrustStore) -> dict:
    """The router's ``access_control`` section for the identities of a trust store."""
    rules, subjects, policies = [], [], []
    for v in store.identities(VEHICLE):
        vr = _vehicle_rules(v)
        rules += vr
        subjects.append({"id": f"vehicle-{v}", "cert_common_names": [v]})
        policies.append({"id": f"policy-{v}", "rules": [r["id"] for r in vr], "subjects": [f"vehicle-{v}"]})
    infra = [n for n in store.identities(INFRASTRUCTURE) if n != "router"]
    if infra:
        rules.append({"id": "infrastructure", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                                   "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                      "key_exprs": [f"{_R}/**"]})
        subjects.append({"id": "infrastructure", "cert_common_names": infra})
        policies.append({"id": "policy-infrastructure", "rules": ["infrastructure"], "subjects": ["infrastructure"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_config(fleet_dir: Path, listen: tuple[str, ...]) -> ZenohConfig:
    """The infrastructure router: TLS listener with the router's certificate and the fleet ACL."""
    store = TrustStore.from_dir(fleet_dir)
    _tls_only(listen)
    return ZenohConfig(mode="router", listen=tuple(listen),
                       extra={"transport/link/tls": tls_settings(fleet_dir, "router", listen=True),
                              "access_control": access_control(store)})


def client_config(fleet_dir: Path, identity: str, connect: tuple[str, ...], lease_ms: int = 2000) -> ZenohConfig:
    """A fleet process (vehicle or infrastructure) connecting to the router as ``identity``."""
    _tls_only(connect)
    return ZenohConfig(mode="client", connect=tuple(connect), lease_ms=lease_ms,
                       extra={"transport/link/tls": tls_settings(fleet_dir, identity)})


def _tls_only(endpoints: tuple[str, ...]) -> None:
    bad = [e for e in endpoints if not e.startswith("tls/")]
    if bad or not endpoints:
        raise ValueError(f"a secured fleet needs tls/<host>:<port> endpoints, got {list(endpoints) or 'none'}")


def as_json5(cfg: ZenohConfig) -> str:
    """A Zenoh configuration file (JSON, which is JSON5) equivalent to ``cfg``."""
    out: dict = {"mode": cfg.mode, "scouting": {"multicast": {"enabled": cfg.multicast_scouting}}}
    if cfg.listen:
        out["listen"] = {"endpoints": list(cfg.listen)}
    if cfg.connect:
        out["connect"] = {"endpoints": list(cfg.connect)}
    for path, value in cfg.extra.items():
        node = out
        parts = path.split("/")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return json.dumps(out, indent=2) + "\n"
