"""Signed beacons and the fleet's trust store (ECDSA P-256 with SHA-256, as IEEE 1609.2).

A fleet has one certificate authority (CA). Every vehicle holds a private key and an X.509
certificate whose common name (CN) is its vehicle id, signed by the CA; the infrastructure router
holds one too (its CN is ``router``, with the host names and addresses it serves as subject
alternative names). The same files serve two purposes:

* beacon signatures (this module): the sender signs the beacon's canonical encoding;
* Zenoh mutual TLS and the router's access control list (``deploy/zenoh/``), where the
  certificate's CN says which vehicle a connection speaks for.

Files of a fleet directory (``slcp keys create DIR V0 V1 ...``)::

    ca.crt  ca.key               the fleet CA (keep ca.key off the vehicles)
    <vehicle>.crt <vehicle>.key  per vehicle, OU=vehicle (keys are PKCS#8 PEM, mode 0600)
    router.crt router.key        the infrastructure router, OU=infrastructure
    emulator.*, recorder.*       infrastructure processes, OU=infrastructure

Wire form of ``Beacon.auth``: 72 bytes, ``key_id`` (8 bytes: the first 8 bytes of the SHA-256 of
the signer's DER SubjectPublicKeyInfo, like 1609.2's HashedId8) followed by the signature
``r || s`` (2 x 32 bytes, big-endian). The signed bytes are the beacon encoded with an empty
``auth``; the beacon's ``t`` (generation time) and ``seq`` are therefore covered, and receivers
reject replayed and stale beacons on them (``agent.runtime``).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import ipaddress
import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import cast

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature, encode_dss_signature
from cryptography.x509.oid import NameOID

from .codec import encode, received_signed_bytes
from .keys import check_name
from .messages import Beacon

log = logging.getLogger(__name__)

KEY_ID_LEN = 8
SIG_LEN = 64
AUTH_LEN = KEY_ID_LEN + SIG_LEN
_CURVE = ec.SECP256R1()
_ALG = ec.ECDSA(hashes.SHA256())

#: certificate roles (the subject's organisational unit)
VEHICLE = "vehicle"
INFRASTRUCTURE = "infrastructure"

#: verification outcomes other than "ok"; receivers count each as ``beacon_<outcome>``
REJECTIONS = ("unsigned", "malformed_auth", "unknown_key", "wrong_vehicle", "bad_signature")


class SecurityError(ValueError):
    """A key, certificate or trust directory is missing or invalid (the message names the file)."""


def key_id(public_key: ec.EllipticCurvePublicKey) -> bytes:
    """HashedId8-style key identifier: first 8 bytes of SHA-256 of the DER public key."""
    der = public_key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    return hashlib.sha256(der).digest()[:KEY_ID_LEN]


def signed_bytes(beacon: Beacon) -> bytes:
    """The bytes a signature covers: the beacon encoded with an empty ``auth``."""
    return encode(dataclasses.replace(beacon, auth=b""))


# ----------------------------------------------------------------------------- signing
class BeaconSigner:
    """Signs a vehicle's beacons with its private key."""

    def __init__(self, vehicle: str, private_key: ec.EllipticCurvePrivateKey) -> None:
        if not isinstance(private_key, ec.EllipticCurvePrivateKey) or private_key.curve.name != _CURVE.name:
            raise SecurityError(f"{vehicle}: the signing key must be an ECDSA P-256 key")
        self.vehicle = check_name(vehicle)
        self._key = private_key
        self.key_id = key_id(private_key.public_key())

    @classmethod
    def from_file(cls, vehicle: str, path: Path | str) -> BeaconSigner:
        return cls(vehicle, _load_private_key(Path(path)))

    def sign(self, beacon: Beacon) -> Beacon:
        """A copy of ``beacon`` with its ``auth`` block filled in."""
        if beacon.vehicle != self.vehicle:
            raise ValueError(f"signer of {self.vehicle} asked to sign a beacon of {beacon.vehicle}")
        der = self._key.sign(signed_bytes(beacon), _ALG)
        r, s = decode_dss_signature(der)
        return dataclasses.replace(beacon, auth=self.key_id + r.to_bytes(32, "big") + s.to_bytes(32, "big"))


# ----------------------------------------------------------------------------- verifying
class TrustStore:
    """The public keys a receiver accepts: CA-signed vehicle certificates, by key id.

    Parameters
    ----------
    ca_cert : x509.Certificate
        The fleet CA.
    certificates : iterable of x509.Certificate
        Vehicle certificates; any not signed by the CA, outside its validity period, without a
        valid CN or not on P-256 is refused with :class:`SecurityError`.
    """

    def __init__(self, ca_cert: x509.Certificate, certificates: Iterable[x509.Certificate]) -> None:
        self.ca = ca_cert
        #: certificate files :meth:`from_dir` refused, with the reason
        self.refused: dict[Path, str] = {}
        self._keys: dict[bytes, tuple[str, ec.EllipticCurvePublicKey]] = {}
        self.roles: dict[str, str] = {}  #: every valid identity (CN) -> role
        now = _dt.datetime.now(_dt.UTC)
        for cert in certificates:
            cn = _common_name(cert)
            try:
                cert.verify_directly_issued_by(ca_cert)
            except (ValueError, TypeError, InvalidSignature) as exc:
                raise SecurityError(f"certificate of {cn!r} is not signed by the fleet CA ({exc})") from None
            if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
                raise SecurityError(f"certificate of {cn!r} is outside its validity period")
            pk = cert.public_key()
            if not isinstance(pk, ec.EllipticCurvePublicKey) or pk.curve.name != _CURVE.name:
                raise SecurityError(f"certificate of {cn!r}: not an ECDSA P-256 key")
            self.roles[cn] = role_of(cert)
            if self.roles[cn] == VEHICLE:  # infrastructure never signs beacons
                self._keys[key_id(pk)] = (cn, pk)

    @classmethod
    def from_dir(cls, directory: Path | str) -> TrustStore:
        """Load ``ca.crt`` and every other ``*.crt`` of ``directory``. A certificate that cannot
        be read or is not valid (another CA, expired, a wrong key or name) is refused alone, its
        file and reason kept in :attr:`refused` and logged: one bad peer certificate must not
        stop a fleet."""
        d = Path(directory)
        ca = _load_cert(d / "ca.crt")
        good: list[x509.Certificate] = []
        refused: dict[Path, str] = {}
        for p in sorted(d.glob("*.crt")):
            if p.name == "ca.crt":
                continue
            try:
                cert = _load_cert(p)
                cls(ca, [cert])  # checked alone
            except SecurityError as exc:
                refused[p] = str(exc).removeprefix(f"{p}: ")
                log.warning("%s: certificate refused: %s", p, refused[p])
                continue
            good.append(cert)
        if not good:
            why = "; ".join(f"{p.name}: {r}" for p, r in refused.items())
            raise SecurityError(f"{d}: no valid vehicle certificates (*.crt)" + (f" ({why})" if why else ""))
        store = cls(ca, good)
        store.refused = refused
        return store

    def vehicles(self) -> list[str]:
        return sorted(v for v, _ in self._keys.values())

    def identities(self, role: str) -> list[str]:
        """The identities (certificate CNs) of a role."""
        return sorted(n for n, r in self.roles.items() if r == role)

    def is_vehicle(self, name: str) -> bool:
        """Whether ``name`` is a vehicle of the fleet (a valid vehicle certificate's CN)."""
        return self.roles.get(name) == VEHICLE

    def key_ids(self) -> dict[str, bytes]:
        """Identity (certificate CN) -> key id."""
        return {v: kid for kid, (v, _) in sorted(self._keys.items(), key=lambda kv: kv[1][0])}

    def verify(self, beacon: Beacon) -> str:
        """``"ok"`` or the reason the beacon is refused (one of :data:`REJECTIONS`)."""
        return self.precheck(beacon) or self.check_signature(beacon)

    def precheck(self, beacon: Beacon) -> str:
        """The checks that cost no signature verification: ``""`` if the beacon is signed with
        the key of the fleet vehicle it names, else the reason it is refused."""
        return self.precheck_fields(beacon.vehicle, beacon.auth)

    def precheck_fields(self, vehicle: str, auth: bytes) -> str:
        """:meth:`precheck` on a beacon's sender and authenticator alone (see
        :func:`transport.codec.peek_beacon`); thread-safe (it only reads)."""
        if not auth:
            return "unsigned"
        if len(auth) != AUTH_LEN:
            return "malformed_auth"
        entry = self._keys.get(bytes(auth[:KEY_ID_LEN]))
        if entry is None:
            return "unknown_key"
        if entry[0] != vehicle:  # a valid key speaking for another vehicle
            return "wrong_vehicle"
        return ""

    def check_signature(self, beacon: Beacon) -> str:
        """``"ok"`` or ``"bad_signature"`` for a beacon that passed :meth:`precheck` (ECDSA)."""
        auth = beacon.auth
        _, pk = self._keys[bytes(auth[:KEY_ID_LEN])]
        r = int.from_bytes(auth[KEY_ID_LEN:KEY_ID_LEN + 32], "big")
        s = int.from_bytes(auth[KEY_ID_LEN + 32:], "big")
        sig = encode_dss_signature(r, s)
        # the bytes as received first (no re-encoding); the canonical encoding only if those
        # fail and differ from it (a sender whose packer is not this codec's)
        received = received_signed_bytes(beacon)
        if received is not None:
            try:
                pk.verify(sig, received, _ALG)
                return "ok"
            except (InvalidSignature, ValueError):
                pass
        canonical = signed_bytes(beacon)
        if canonical == received:
            return "bad_signature"
        try:
            pk.verify(sig, canonical, _ALG)
        except (InvalidSignature, ValueError):
            return "bad_signature"
        return "ok"


# ----------------------------------------------------------------------------- key creation
def create_fleet(directory: Path | str, vehicles: list[str], router_hosts: tuple[str, ...] = ("127.0.0.1", "localhost"),
                 days: int = 365, overwrite: bool = False, infrastructure: tuple[str, ...] = ("emulator", "recorder"),
                 new_ca: bool = False) -> list[Path]:
    """Create a fleet CA, a key and certificate per vehicle, the router's and one per
    infrastructure process (``infrastructure``: the emulator, the recorder); returns the files.

    The certificate's organisational unit (OU) is its role: ``vehicle`` or ``infrastructure``
    (the router is infrastructure). Only vehicle certificates sign beacons; the router's access
    control gives infrastructure the whole ``slcp/v1/**`` space. Existing files are kept:
    re-running adds missing identities with the existing CA, ``overwrite`` re-issues the listed
    vehicles' keys and certificates with it, and only ``new_ca`` replaces the CA (and then every
    identity, since the old certificates no longer verify). Private keys are written with mode
    0600, existing ones included.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise SecurityError(f"{d}: not a folder (the fleet's keys go in a folder)")
    if days < 1:
        raise SecurityError(f"days must be at least 1, got {days}")
    d.mkdir(parents=True, exist_ok=True)
    for v in vehicles:
        check_name(v)
        if v in ("ca", "router", *infrastructure):
            raise SecurityError(f"{v!r} is reserved; choose another vehicle id")
    for v in infrastructure:
        check_name(v)
    written: list[Path] = []
    if new_ca:  # every vehicle of the directory, whose certificate the new CA must re-issue
        known = {p.stem for p in d.glob("*.crt")} - {"ca", "router", *infrastructure}
        vehicles = [*vehicles, *sorted(known - set(vehicles))]
    if new_ca or not (d / "ca.crt").exists():
        ca_key = ec.generate_private_key(_CURVE)
        ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "slcp fleet CA")])
        ca_cert = (
            _builder(ca_name, ca_name, ca_key.public_key(), days)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        written += _write_pair(d, "ca", ca_key, ca_cert)
    else:
        ca_key = _load_private_key(d / "ca.key")
        ca_cert = _load_cert(d / "ca.crt")
    # a certificate valid past its CA's end would not verify then: it ends with the CA
    ca_end = ca_cert.not_valid_after_utc
    issued = len(written)
    identities = ([(v, VEHICLE, ()) for v in vehicles] + [("router", INFRASTRUCTURE, router_hosts)]
                  + [(v, INFRASTRUCTURE, ()) for v in infrastructure])
    for name, role, sans in identities:
        if (d / f"{name}.crt").exists() and not new_ca and not (overwrite and name in vehicles):
            continue
        key = ec.generate_private_key(_CURVE)
        subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role),
                             x509.NameAttribute(NameOID.COMMON_NAME, name)])
        # key identifiers: RFC 5280 asks for them, and path validators of the web-PKI profile
        # refuse a leaf without the authority's (the fleet CA's key is P-256, a key that can issue)
        ca_public_key = cast(ec.EllipticCurvePublicKey, ca_cert.public_key())
        b = (_builder(subject, ca_cert.subject, key.public_key(), days, ca_end)
             .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
             .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_public_key), critical=False)
             .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False))
        alt: list[x509.GeneralName] = [x509.DNSName(name)]
        for h in sans:
            try:
                alt.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                alt.append(x509.DNSName(h))
        b = b.add_extension(x509.SubjectAlternativeName(alt), critical=False)
        written += _write_pair(d, name, key, b.sign(ca_key, hashes.SHA256()))
    if len(written) > issued and _dt.datetime.now(_dt.UTC) + _dt.timedelta(days=days) > ca_end + _dt.timedelta(days=1):
        log.warning("the new certificates are valid to the fleet CA's end (%s), not for %d days: a new CA (--new-ca) "
                    "for longer", f"{ca_end:%Y-%m-%d}", days)
    return written


def _builder(subject: x509.Name, issuer: x509.Name, public_key: ec.EllipticCurvePublicKey,
             days: int, not_after: _dt.datetime | None = None) -> x509.CertificateBuilder:
    """A certificate valid from now (less 5 minutes of clock skew) for ``days``, and at most to
    ``not_after``."""
    now = _dt.datetime.now(_dt.UTC)
    end = now + _dt.timedelta(days=days)
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(end if not_after is None else min(end, not_after)))


def _write_pair(d: Path, name: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate) -> list[Path]:
    kp, cp = d / f"{name}.key", d / f"{name}.crt"
    fd = os.open(kp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # an existing file keeps its mode through open()
    with os.fdopen(fd, "wb") as f:
        f.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption()))
    cp.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return [kp, cp]


def _load_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except OSError as exc:
        raise SecurityError(f"{path}: cannot read ({exc.strerror})") from None
    except ValueError as exc:
        raise SecurityError(f"{path}: not a PEM certificate ({exc})") from None


def _load_private_key(path: Path) -> ec.EllipticCurvePrivateKey:
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise SecurityError(f"{path}: cannot read ({exc.strerror})") from None
    if mode & 0o077:
        raise SecurityError(f"{path}: private key readable by others (mode {mode & 0o777:o}); chmod 600 it")
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except OSError as exc:
        raise SecurityError(f"{path}: cannot read ({exc.strerror})") from None
    except (ValueError, TypeError) as exc:
        raise SecurityError(f"{path}: not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise SecurityError(f"{path}: not an elliptic-curve key")
    return key


def role_of(cert: x509.Certificate) -> str:
    """``vehicle`` or ``infrastructure`` (the subject's OU; anything else is an error)."""
    attrs = cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)
    role = str(attrs[0].value) if attrs else ""
    if role not in (VEHICLE, INFRASTRUCTURE):
        raise SecurityError(f"certificate {cert.subject.rfc4514_string()!r}: OU must be {VEHICLE} or {INFRASTRUCTURE}")
    return role


def _common_name(cert: x509.Certificate) -> str:
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    cn = attrs[0].value if attrs else ""
    try:
        return check_name(str(cn))
    except ValueError:
        raise SecurityError(
            f"certificate with subject {cert.subject.rfc4514_string()!r}: CN is not a vehicle id"
        ) from None
