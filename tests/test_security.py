"""Signed beacons: sign/verify round trips over the codec, and every way a beacon is refused
(unsigned, tampered, unknown key, another vehicle's key, malformed, replayed, stale), at the trust
store and at a running agent."""

from __future__ import annotations

import asyncio
import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from slcp.agent.runtime import Agent
from slcp.deploy.agent_configs import agent_config
from slcp.deploy.processes import ConfigError, load_agent_config
from slcp.hw_emulation.scenario import load_scenario
from slcp.transport.bus import InMemoryNetwork
from slcp.transport.codec import decode, encode, received_signed_bytes
from slcp.transport.messages import Beacon
from slcp.transport.security import AUTH_LEN, BeaconSigner, SecurityError, TrustStore, create_fleet, signed_bytes


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fleet")
    create_fleet(d, ["V0", "V1", "V2"])
    return d


def beacon(vehicle: str = "V1", seq: int = 7, t: float = 100.0, method: str = "CP") -> Beacon:
    return Beacon(vehicle, seq, method, t, np.array([0.7, 2.0, 50.0]), np.array([5.0, 0.0, 0.0]),
                  np.diag([1.0, 2.0, 4.0]), first_stopped=True)


def test_a_signed_beacon_survives_the_wire_and_verifies(fleet) -> None:
    signer = BeaconSigner.from_file("V1", fleet / "V1.key")
    store = TrustStore.from_dir(fleet)
    b = decode(encode(signer.sign(beacon())))
    assert len(b.auth) == AUTH_LEN and b.auth[:8] == signer.key_id
    assert store.verify(b) == "ok"
    assert store.vehicles() == ["V0", "V1", "V2"]  # only vehicles sign beacons
    assert store.identities("infrastructure") == ["emulator", "recorder", "router"]


def test_every_forgery_is_refused_with_its_reason(fleet, tmp_path) -> None:
    store = TrustStore.from_dir(fleet)
    signed = BeaconSigner.from_file("V1", fleet / "V1.key").sign(beacon())
    assert store.verify(beacon()) == "unsigned"
    # any signed field changed after signing
    for change in ({"llh": signed.llh + [1e-7, 0, 0]}, {"t": 100.2}, {"seq": 8}, {"first_stopped": False},
                   {"cov_pos": signed.cov_pos * 0.01}, {"method": "SL-CP"}):
        assert store.verify(dataclasses.replace(signed, **change)) == "bad_signature", change
    # V1's valid signature presented as V2's beacon
    assert store.verify(dataclasses.replace(signed, vehicle="V2")) == "wrong_vehicle"
    # V2 cannot sign for V1 with its own key either
    v2 = BeaconSigner.from_file("V2", fleet / "V2.key")
    with pytest.raises(ValueError, match="asked to sign a beacon of V1"):
        v2.sign(beacon("V1"))
    forged = dataclasses.replace(v2.sign(beacon("V2")), vehicle="V1")
    assert store.verify(forged) == "wrong_vehicle"
    # a key of another fleet
    other = tmp_path / "other"
    create_fleet(other, ["V1"])
    assert store.verify(BeaconSigner.from_file("V1", other / "V1.key").sign(beacon())) == "unknown_key"
    # malformed auth blocks
    assert store.verify(dataclasses.replace(signed, auth=signed.auth[:-1])) == "malformed_auth"
    assert store.verify(dataclasses.replace(signed, auth=signed.auth[:8] + bytes(64))) == "bad_signature"
    flipped = bytearray(signed.auth)
    flipped[20] ^= 1
    assert store.verify(dataclasses.replace(signed, auth=bytes(flipped))) == "bad_signature"


def test_a_received_beacon_is_verified_over_its_bytes_as_sent_or_else_re_encoded(fleet) -> None:
    """The verifier checks a decoded beacon's signature over its payload with an empty auth
    (no re-encoding): for this codec's packer that is the canonical encoding itself. A sender
    whose packer orders the fields otherwise still verifies (against the canonical encoding),
    and a tampered payload fails either way."""
    import msgpack

    store = TrustStore.from_dir(fleet)
    b = dataclasses.replace(beacon(), sources=((("V1",), np.diag([1.0, 2.0, 4.0])),),
                            constants=(("V1~gap", np.array([0.1, 0.2, 0.0])),))
    signed = BeaconSigner.from_file("V1", fleet / "V1.key").sign(b)
    got = decode(encode(signed))
    assert received_signed_bytes(got) == signed_bytes(got) and store.verify(got) == "ok"
    assert received_signed_bytes(signed) is None and received_signed_bytes(beacon()) is None
    # the same fields packed in reverse order: other bytes, the same beacon
    obj = msgpack.unpackb(encode(signed), raw=False)
    other = msgpack.packb(dict(reversed(list(obj.items()))), use_bin_type=True)
    assert other != encode(signed)
    got = decode(other)
    assert received_signed_bytes(got) != signed_bytes(got) and store.verify(got) == "ok"
    obj["t"] = 100.5
    for packed in (msgpack.packb(obj, use_bin_type=True), msgpack.packb(dict(reversed(list(obj.items()))),
                                                                        use_bin_type=True)):
        assert store.verify(decode(packed)) == "bad_signature"


def test_the_signature_covers_every_field_but_its_own(fleet) -> None:
    """Each field a receiver reads, changed after signing, breaks the signature: the velocity
    (which the misbehaviour detector extrapolates with), the covariance by source and the
    constants' sensitivities (which the fusion rules weigh) as much as the position."""
    store = TrustStore.from_dir(fleet)
    b = dataclasses.replace(beacon(), sources=((("V1",), np.diag([1.0, 2.0, 4.0])),),
                            constants=(("V1~gap", np.array([0.1, 0.2, 0.0])),))
    signed = BeaconSigner.from_file("V1", fleet / "V1.key").sign(b)
    assert store.verify(signed) == "ok"
    changes = {
        "seq": 8, "method": "SL-CP", "t": 100.2, "first_stopped": False,
        "llh": signed.llh + [1e-7, 0, 0], "v_ned": signed.v_ned + [0.0, 0.01, 0.0],
        "cov_pos": signed.cov_pos * 1.01,
        "sources": ((("V1",), np.diag([1.0, 2.0, 4.1])),),
        "constants": (("V1~gap", np.array([0.1, 0.3, 0.0])),),
    }
    assert set(changes) == {f.name for f in dataclasses.fields(Beacon)} - {"vehicle", "auth"}
    for name, value in changes.items():
        assert store.verify(dataclasses.replace(signed, **{name: value})) == "bad_signature", name
        assert store.verify(decode(encode(dataclasses.replace(signed, **{name: value})))) == "bad_signature", name


def test_a_certificate_not_issued_by_the_fleet_ca_is_refused(fleet, tmp_path, caplog) -> None:
    other = tmp_path / "other"
    create_fleet(other, ["V9"])
    mixed = tmp_path / "mixed"
    shutil.copytree(fleet, mixed)
    shutil.copy(other / "V9.crt", mixed / "V9.crt")
    # refused alone: the rest of the fleet stays trusted, and the file is named
    store = TrustStore.from_dir(mixed)
    assert "V9" not in store.vehicles() and "V1" in store.vehicles()
    assert "V9" in store.refused[mixed / "V9.crt"] and "not signed by the fleet CA" in store.refused[mixed / "V9.crt"]
    # and the log says which file and why (an operator reads it there)
    assert any(str(mixed / "V9.crt") in r.getMessage() and "not signed by the fleet CA" in r.getMessage()
               for r in caplog.records if r.levelname == "WARNING"), caplog.text
    (tmp_path / "empty").mkdir()
    with pytest.raises(SecurityError, match="ca.crt: cannot read"):
        TrustStore.from_dir(tmp_path / "empty")
    (tmp_path / "bad.key").write_text("not a key")
    (tmp_path / "bad.key").chmod(0o600)
    with pytest.raises(SecurityError, match="not an unencrypted PEM private key"):
        BeaconSigner.from_file("V1", tmp_path / "bad.key")


def test_create_fleet_keeps_existing_keys_and_adds_vehicles(fleet, tmp_path) -> None:
    d = tmp_path / "f"
    create_fleet(d, ["V0"])
    before = (d / "V0.key").read_bytes(), (d / "ca.crt").read_bytes()
    written = create_fleet(d, ["V0", "V5"])
    assert sorted(p.name for p in written) == ["V5.crt", "V5.key"]
    assert ((d / "V0.key").read_bytes(), (d / "ca.crt").read_bytes()) == before
    assert (d / "V5.key").stat().st_mode & 0o077 == 0  # private keys are private
    assert "V5" in TrustStore.from_dir(d).vehicles()
    with pytest.raises(SecurityError, match="reserved"):
        create_fleet(d, ["router"])
    # an infrastructure key cannot sign beacons, not even for its own name
    assert TrustStore.from_dir(d).verify(BeaconSigner.from_file("emulator", d / "emulator.key").sign(
        beacon("emulator"))) == "unknown_key"


def test_a_certificate_never_outlives_its_ca_and_a_file_is_no_fleet_folder(tmp_path, caplog) -> None:
    """A vehicle added for 100,000 days to a CA of 365 ends with the CA, and a warning says so;
    a file where the folder should be is a clear error."""
    from cryptography import x509

    d = tmp_path / "f"
    create_fleet(d, ["V0"], days=365)
    ca_end = x509.load_pem_x509_certificate((d / "ca.crt").read_bytes()).not_valid_after_utc
    create_fleet(d, ["V2"], days=100_000)
    assert x509.load_pem_x509_certificate((d / "V2.crt").read_bytes()).not_valid_after_utc == ca_end
    assert "valid to the fleet CA's end" in caplog.text
    caplog.clear()
    create_fleet(d, ["V3"], days=30)  # within the CA's validity: its own days, no warning
    assert x509.load_pem_x509_certificate((d / "V3.crt").read_bytes()).not_valid_after_utc < ca_end
    assert "fleet CA's end" not in caplog.text
    (tmp_path / "file").write_text("x")
    with pytest.raises(SecurityError, match="not a folder"):
        create_fleet(tmp_path / "file", ["V0"])


def _agent(fleet: Path, vehicle: str = "V0") -> Agent:
    scn = load_scenario("paper-1")
    cfg = dataclasses.replace(agent_config(scn, vehicle), trust=TrustStore.from_dir(fleet),
                              signer=BeaconSigner.from_file(vehicle, fleet / f"{vehicle}.key"))
    return Agent(cfg, InMemoryNetwork().bus())


def test_an_agent_accepts_signed_beacons_and_counts_every_refusal(fleet, tmp_path) -> None:
    agent = _agent(fleet)
    agent.seq.t = 100.0  # the agent's filter time
    v1 = BeaconSigner.from_file("V1", fleet / "V1.key")
    create_fleet(tmp_path / "other", ["V1"])
    intruder = BeaconSigner.from_file("V1", tmp_path / "other" / "V1.key")
    good = v1.sign(beacon(t=99.9))
    cases = [
        (good, None),
        (good, "CP_duplicate_or_old"),  # replayed as it was
        (v1.sign(beacon(seq=3, t=99.8)), "CP_duplicate_or_old"),  # an older one replayed later
        (beacon(t=100.0), "beacon_unsigned"),
        (dataclasses.replace(v1.sign(beacon(t=100.0)), llh=np.array([0.7, 2.0, 60.0])), "beacon_bad_signature"),
        (dataclasses.replace(v1.sign(beacon(t=100.0)), vehicle="V2"), "beacon_wrong_vehicle"),
        (intruder.sign(beacon(t=100.0)), "beacon_unknown_key"),
        (v1.sign(beacon(seq=9, t=98.5)), "beacon_stale"),  # generated 1.5 s before the filter time
        (v1.sign(beacon(seq=9, t=103.0)), "beacon_future"),
    ]
    for b, counter in cases:
        before = dict(agent.counters) | {f"CP_{k}": v for k, v in agent.tables["CP"].counters.items()}
        asyncio.run(agent.handle(decode(encode(b))))
        after = dict(agent.counters) | {f"CP_{k}": v for k, v in agent.tables["CP"].counters.items()}
        changed = {k for k in after if after[k] != before.get(k, 0)} - {"beacons_rx"}
        if counter is None:
            assert changed == {"CP_beacons"}, changed
        else:
            assert changed == {counter}, (counter, changed)
    assert agent.tables["CP"].newest_time("V1") == pytest.approx(99.9)  # only the good one stored
    assert agent.tables["CP"].counters["beacons"] == 1


def test_an_agent_signs_what_it_sends(fleet) -> None:
    agent = _agent(fleet, "V2")
    sent: list[bytes] = []

    class Bus:
        async def publish(self, key, payload):
            sent.append(payload)

    agent.bus = Bus()
    g = np.array([0.3, 0.0, 0.0])  # one random constant's sensitivity, m
    agent.engine.filters = {
        "CP": type(
            "F",
            (),
            {
                "spec": type("S", (), {"ranges": True, "stop_line": False})(),
                "beacon": lambda self: (np.array([0.7, 2.0, 5.0]), np.zeros(3), np.eye(3)),
                "beacon_sources": lambda self: (
                    (("V2",), 0.75 * np.eye(3)),
                    (("V0", "~common"), 0.25 * np.eye(3) - np.outer(g, g)),
                ),
                "beacon_constants": lambda self: (("V2~1.5", g),),
            },
        )()
    }
    agent.engine._next["beacon"] = 10.0
    agent.engine._timers(10.0)
    asyncio.run(agent._publish_outbox())
    store = TrustStore.from_dir(fleet)
    assert len(sent) == 1 and store.verify(decode(sent[0])) == "ok"
    # the breakdown by source is signed with the rest
    b = decode(sent[0])
    assert [lab for lab, _ in b.sources] == [("V2",), ("V0", "~common")]
    assert store.verify(dataclasses.replace(b, sources=((("V2",), np.eye(3)),))) == "bad_signature"
    # and so are the random constants' sensitivities
    assert [name for name, _ in b.constants] == ["V2~1.5"]
    assert store.verify(dataclasses.replace(b, constants=(("V2~1.5", np.zeros(3)),))) == "bad_signature"


def test_security_section_errors_name_the_field(fleet, tmp_path) -> None:
    def cfg(text: str) -> Path:
        p = tmp_path / "agent.toml"
        p.write_text('[agent]\nvehicle = "V1"\n' + text)
        return p

    good, _ = load_agent_config(cfg(f'[security]\ntrust_dir = "{fleet}"\n'), None)
    assert good.signer is not None and good.signer.vehicle == "V1" and good.trust is not None
    for text, msg in [('[security]\nkey = "x.key"\n', "security.trust_dir: missing"),
                      (f'[security]\ntrust_dir = "{fleet}"\nkeyfile = "x"\n', "security.keyfile: unknown field"),
                      (f'[security]\ntrust_dir = "{fleet}"\nkey = "missing.key"\n', "missing.key: cannot read"),
                      (f'[security]\ntrust_dir = "{tmp_path}"\n', "ca.crt: cannot read"),
                      ('[securty]\ntrust_dir = "x"\n', r"\[securty\]: unknown section")]:
        with pytest.raises(ConfigError, match=msg):
            load_agent_config(cfg(text), None)
    create_fleet(tmp_path / "small", ["V0"])
    with pytest.raises(ConfigError, match="no valid vehicle certificate for V1"):
        load_agent_config(cfg(f'[security]\ntrust_dir = "{tmp_path / "small"}"\nkey = "{fleet / "V1.key"}"\n'), None)


def test_the_fleet_is_a_valid_x509_pki_for_tls(tmp_path) -> None:
    """What ``create_fleet`` writes, checked as TLS will check it: the router's certificate
    validates for 127.0.0.1 and localhost, and a vehicle's as a client, under a path validator
    (cryptography's, the web-PKI profile: a CA limited to signing certificates, critical basic
    constraints, leaves that are no CA); and the profile field by field."""
    import datetime as dt
    import ipaddress

    from cryptography import x509
    from cryptography.x509.oid import NameOID
    from cryptography.x509.verification import PolicyBuilder, Store

    d = tmp_path / "a" / "b"  # created with its parents
    written = create_fleet(d, ["V0"], days=30)
    assert sorted(p.name for p in written) == sorted(f"{n}.{e}" for n in ("ca", "V0", "router", "emulator", "recorder")
                                                    for e in ("key", "crt"))
    certs = {p.stem: x509.load_pem_x509_certificate(p.read_bytes()) for p in written if p.suffix == ".crt"}
    ca = certs["ca"]
    assert ca.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "slcp fleet CA"
    bc = ca.extensions.get_extension_for_class(x509.BasicConstraints)
    assert bc.critical and bc.value.ca and bc.value.path_length == 0
    ku = ca.extensions.get_extension_for_class(x509.KeyUsage)
    assert ku.critical and ku.value.key_cert_sign and ku.value.crl_sign
    assert not (ku.value.digital_signature or ku.value.key_encipherment or ku.value.content_commitment
                or ku.value.data_encipherment or ku.value.key_agreement)
    for name, cert in certs.items():
        life = cert.not_valid_after_utc - cert.not_valid_before_utc
        assert dt.timedelta(days=30) < life <= dt.timedelta(days=30, minutes=6), name
        if name == "ca":
            continue
        bc = cert.extensions.get_extension_for_class(x509.BasicConstraints)
        assert bc.critical and not bc.value.ca
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
        assert not san.critical and name in san.value.get_values_for_type(x509.DNSName)
    san = certs["router"].extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
    assert "localhost" in san.get_values_for_type(x509.DNSName)
    store = Store([ca])
    for host in (x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")):
        PolicyBuilder().store(store).build_server_verifier(host).verify(certs["router"], [])
    PolicyBuilder().store(store).build_client_verifier().verify(certs["V0"], [])
    for reserved in ("ca", "router", "emulator", "recorder"):
        with pytest.raises(SecurityError, match="reserved"):
            create_fleet(tmp_path / "r", [reserved])


def test_each_bad_key_or_certificate_is_refused_with_its_reason(fleet, tmp_path) -> None:
    """Keys and certificates that are not the fleet's P-256 profile, expired or not yet valid,
    without a role or a vehicle id, or not PEM at all: each refusal says what is wrong."""
    import datetime as dt

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec, rsa
    from cryptography.x509.oid import NameOID

    with pytest.raises(SecurityError, match="V1: the signing key must be an ECDSA P-256 key"):
        BeaconSigner("V1", ec.generate_private_key(ec.SECP384R1()))
    with pytest.raises(SecurityError, match="V1: the signing key must be an ECDSA P-256 key"):
        BeaconSigner("V1", rsa.generate_private_key(65537, 2048))
    rsa_pem = tmp_path / "rsa.key"
    rsa_pem.write_bytes(rsa.generate_private_key(65537, 2048).private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
    rsa_pem.chmod(0o600)
    with pytest.raises(SecurityError, match="rsa.key: not an elliptic-curve key"):
        BeaconSigner.from_file("V1", rsa_pem)
    ca_key = serialization.load_pem_private_key((fleet / "ca.key").read_bytes(), None)
    ca = x509.load_pem_x509_certificate((fleet / "ca.crt").read_bytes())
    now = dt.datetime.now(dt.UTC)

    def cert(cn: str = "V7", ou: str | None = "vehicle", key=None, start=-1.0, days=10.0) -> x509.Certificate:
        attrs = ([x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, ou)] if ou else []) + \
            [x509.NameAttribute(NameOID.COMMON_NAME, cn)]
        key = key or ec.generate_private_key(ec.SECP256R1())
        return (x509.CertificateBuilder().subject_name(x509.Name(attrs)).issuer_name(ca.subject)
                .public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(now + dt.timedelta(days=start)).not_valid_after(now + dt.timedelta(days=start + days))
                .sign(ca_key, hashes.SHA256()))

    assert TrustStore(ca, [cert()]).vehicles() == ["V7"]
    for bad, match in [
        (cert(start=-20.0), "certificate of 'V7' is outside its validity period"),  # expired
        (cert(start=1.0), "certificate of 'V7' is outside its validity period"),  # not yet valid
        (cert(key=ec.generate_private_key(ec.SECP384R1())), "certificate of 'V7': not an ECDSA P-256 key"),
        (cert(ou=None), "OU must be vehicle or infrastructure"),
        (cert(ou="guest"), "OU must be vehicle or infrastructure"),
        (cert(cn="not a name!"), "CN is not a vehicle id"),
    ]:
        with pytest.raises(SecurityError, match=match):
            TrustStore(ca, [bad])
    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(fleet / "ca.crt", d / "ca.crt")
    with pytest.raises(SecurityError, match="d: no valid vehicle certificates"):
        TrustStore.from_dir(d)
    (d / "V1.crt").write_text("garbage")
    with pytest.raises(SecurityError, match="V1.crt: not a PEM certificate"):
        TrustStore.from_dir(d)


def test_keys_never_replace_a_fleet_ca_without_its_own_flag(tmp_path, capsys) -> None:
    """#39 finding 7: `keys create DIR V1 --force` replaced the CA and left the other vehicles'
    certificates unverifiable. Now --force re-issues V1 with the existing CA, --new-ca alone
    replaces it (and re-issues every identity of the directory), and key files are 0600 even
    when they existed with another mode."""
    from slcp.deploy.cli import main

    d = tmp_path / "fleet"
    assert main(["keys", "create", str(d), "V0", "V1", "V2"]) == 0
    ca = (d / "ca.crt").read_bytes()
    v0, v1 = (d / "V0.crt").read_bytes(), (d / "V1.crt").read_bytes()
    (d / "V1.key").chmod(0o644)
    assert main(["keys", "create", str(d), "V1", "--force"]) == 0
    assert (d / "ca.crt").read_bytes() == ca and (d / "V0.crt").read_bytes() == v0
    assert (d / "V1.crt").read_bytes() != v1 and (d / "V1.key").stat().st_mode & 0o777 == 0o600
    assert TrustStore.from_dir(d).vehicles() == ["V0", "V1", "V2"] and not TrustStore.from_dir(d).refused
    assert main(["keys", "create", str(d), "V1", "--new-ca"]) == 0
    assert (d / "ca.crt").read_bytes() != ca and (d / "V0.crt").read_bytes() != v0
    store = TrustStore.from_dir(d)
    assert store.vehicles() == ["V0", "V1", "V2"] and not store.refused  # all re-issued
    capsys.readouterr()


def test_a_world_readable_key_is_refused_and_a_bad_peer_certificate_disables_that_peer_alone(fleet, tmp_path):
    from slcp.deploy.processes import ConfigError, load_agent_config

    d = tmp_path / "fleet"
    shutil.copytree(fleet, d)
    (d / "V1.key").chmod(0o644)
    with pytest.raises(SecurityError, match=r"V1.key: private key readable by others \(mode 644\); chmod 600"):
        BeaconSigner.from_file("V1", d / "V1.key")
    (d / "V1.key").chmod(0o600)
    (d / "V2.crt").write_text((d / "V2.crt").read_text()[:200])  # truncated
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f'[agent]\nvehicle = "V1"\n[security]\ntrust_dir = "{d}"\n')
    agent, _ = load_agent_config(cfg, None)  # V1 starts; V2 alone is not trusted
    assert "V2" not in agent.trust.vehicles() and "V1" in agent.trust.vehicles()
    assert "not a PEM certificate" in agent.trust.refused[d / "V2.crt"]
    cfg.write_text(f'[agent]\nvehicle = "V2"\n[security]\ntrust_dir = "{d}"\n')
    with pytest.raises(ConfigError, match=r"no valid vehicle certificate for V2 .*V2.crt: not a PEM certificate"):
        load_agent_config(cfg, None)


def test_stale_future_and_replayed_beacons_cost_no_signature_verification() -> None:
    """#39 finding 6: every refused beacon cost a full ECDSA verification. The time window and
    the replay check come first: a flood of stale, future-dated or replayed beacons verifies
    nothing, and a genuine one is still verified and taken."""
    import dataclasses as dc

    from slcp.agent.engine import VehicleEngine
    from slcp.deploy.agent_configs import agent_config
    from slcp.deploy.inprocess import run_inprocess
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth
    class CountingTrust:
        calls = 0

        def precheck(self, beacon) -> str:
            return ""

        def check_signature(self, beacon) -> str:
            CountingTrust.calls += 1
            return "ok"

    scn = dc.replace(load_scenario("paper-1"), duration=6.0)
    inputs: list = []
    run_inprocess(build_truth(scn), seed=0, methods=("CP",),
                  on_message=lambda v, m: inputs.append(m) if v == "V1" else None)
    eng = VehicleEngine(dc.replace(agent_config(scn, "V1", ("CP",)), trust=CountingTrust()))
    for m in inputs:
        if not isinstance(m, Beacon):
            eng.handle(m)
    now = eng.seq.t
    assert now is not None and now > 3.0
    genuine = Beacon("V0", 1, "CP", now - 0.05, np.array([0.7, -1.8, 100.0]), np.zeros(3), np.eye(3))
    eng.handle(genuine)
    assert CountingTrust.calls == 1 and eng.tables["CP"].newest_time("V0") == genuine.t
    for k in range(300):
        eng.handle(dc.replace(genuine, seq=2 + k, t=now - 100.0))  # stale
        eng.handle(dc.replace(genuine, seq=400 + k, t=now + 100.0))  # future-dated
        eng.handle(dc.replace(genuine, seq=800 + k))  # replayed
    assert CountingTrust.calls == 1
    assert eng.counters["beacon_stale"] == 300 and eng.counters["beacon_future"] == 300
    assert eng.tables["CP"].counters["duplicate_or_old"] == 300


def test_a_flood_in_one_vehicles_name_costs_a_bounded_number_of_verifications(fleet) -> None:
    """#39 finding 6: every forged beacon with a fleet key id and a fresh time cost an ECDSA
    verification. Per sender and method the verifications are a token bucket on the filter time
    (twice the beacon rate, two seconds of burst): 10,000 forgeries in V0's name in 1 s of filter
    time cost at most 20 + 10 verifications, and V2's genuine beacons meanwhile are all verified
    and taken."""
    import dataclasses as dc

    from slcp.agent.engine import VehicleEngine

    from conftest import count_verifications

    trust = TrustStore.from_dir(fleet)
    calls = count_verifications(trust)
    scn = load_scenario("paper-1")
    eng = VehicleEngine(dc.replace(agent_config(scn, "V1", ("CP",)), trust=trust))
    eng.seq.t = 100.0  # a running filter's time (the budget runs on it)
    forged = BeaconSigner.from_file("V0", fleet / "V0.key").sign(beacon("V0", t=100.0))
    forged = dc.replace(forged, auth=forged.auth[:-1] + bytes([forged.auth[-1] ^ 1]))  # a bad signature
    v2 = BeaconSigner.from_file("V2", fleet / "V2.key")
    for k in range(10_000):
        eng.seq.t = 100.0 + k * 1e-4  # 1 s of filter time
        eng.handle(dc.replace(forged, seq=10 + k, t=eng.seq.t + 0.5))
        if k % 2000 == 0:  # V2 at its beacon rate
            eng.handle(v2.sign(beacon("V2", seq=k, t=eng.seq.t)))
    rate = 2.0 * eng.cfg.beacon_rate
    assert eng.counters["beacon_bad_signature"] <= 2 * rate + rate * 1.0 + 1
    assert eng.counters["beacon_verify_budget"] == 10_000 - eng.counters["beacon_bad_signature"]
    assert calls["n"] == eng.counters["beacon_bad_signature"] + 5
    assert eng.beacons_from.get("V2") == 5 and "V0" not in eng.beacons_from


def test_a_replay_is_refused_after_its_sender_left_the_tables(fleet) -> None:
    """The replay check remembers a sender's newest verified beacon after the sender leaves the
    tables (its liveliness token gone, or silent past the table timeout): its last beacons,
    replayed within the time window, are still refused."""
    import dataclasses as dc

    from slcp.agent.engine import VehicleEngine

    trust = TrustStore.from_dir(fleet)
    eng = VehicleEngine(dc.replace(agent_config(load_scenario("paper-1"), "V1", ("CP",)), trust=trust))
    eng.seq.t = 100.0
    v0 = BeaconSigner.from_file("V0", fleet / "V0.key")
    genuine = v0.sign(beacon("V0", seq=3, t=99.9))
    eng.handle(genuine)
    assert eng.beacons_from == {"V0": 1} and eng.tables["CP"].newest_time("V0") == 99.9
    eng.neighbour_alive("V0", False)  # its agent stopped: the tables forget it
    assert eng.tables["CP"].newest_time("V0") is None
    eng.handle(genuine)  # replayed, still inside the 1 s window
    assert eng.beacons_from == {"V0": 1} and eng.tables["CP"].counters["duplicate_or_old"] == 1
    eng.handle(v0.sign(beacon("V0", seq=4, t=100.1)))  # a newer one is taken
    assert eng.beacons_from == {"V0": 2}
