"""Certificates for a secured bus: one certificate authority and one certificate per identity.

An identity is the certificate's common name (CN); the access-control policy of
:mod:`bttsim_stream.bus.security` grants rights by it. A folder made by
:func:`generate_certificates` holds ``ca.pem`` (the CA certificate every node trusts),
``ca-key.pem`` (the CA's private key: keep it off the nodes), and ``<name>.pem`` /
``<name>-key.pem`` for every identity. Keys are ECDSA P-256 in PKCS#8 PEM; certificates are
valid for both TLS client and server authentication, for ``localhost``, ``127.0.0.1``, ``::1``
and any extra host names or addresses given (the names a connecting node checks against the
endpoint it dials).
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import re
import os
from pathlib import Path

from ..errors import BttsimError

__all__ = ["IDENTITIES", "generate_certificates"]

#: The identities of a run: the four nodes, the router, and ``run`` (``bttsim run``'s own
#: session, which follows the progress).
IDENTITIES = ("sim", "processor", "recorder", "viewer", "router", "run")
_LOCAL = ("localhost", "127.0.0.1", "::1")
#: The longest validity ``bttsim certs --days`` gives (100 years; X.509 dates end in 9999).
MAX_DAYS = 36_500


def _x509():
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:  # pragma: no cover - a declared dependency
        raise BttsimError("certificates need the 'cryptography' package (pip install cryptography)") from None
    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


#: A DNS name: dot-separated labels of letters, digits, '_' and '-' (not '-' at either end),
#: 1-63 each; a first label '*' (a wildcard).
_DNS_NAME = re.compile(r"(\*|(?!-)[A-Za-z0-9_-]{1,63}(?<!-))(\.(?!-)[A-Za-z0-9_-]{1,63}(?<!-))*\.?")


def _san_entries(x509, hosts):
    out = []
    for h in dict.fromkeys([*_LOCAL, *hosts]):
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            if not _DNS_NAME.fullmatch(str(h)) or len(h) > 253 or re.fullmatch(r"[0-9.]+", h):
                raise BttsimError(f"bad host name {h!r} for a certificate (an IP address, or a DNS name: labels of "
                                  "letters, digits, '_' and '-' joined by dots, '*' first for a wildcard)") from None
            out.append(x509.DNSName(h))
    return out


def generate_certificates(folder, names=IDENTITIES, *, hosts=(), days: int = 365, overwrite: bool = False) -> dict:
    """Write a CA and one certificate per name into ``folder``; returns ``{name: Path}`` of the
    certificates (``"ca"`` included).

    Parameters
    ----------
    folder : path
        Created if missing.
    names : sequence of str
        Identities (certificate common names), ``[A-Za-z0-9_-]+``.
    hosts : sequence of str
        Extra DNS names or IP addresses the certificates are valid for (besides loopback).
    days : int
        Validity, from now.
    overwrite : bool
        Replace existing files (otherwise an existing ``ca.pem`` is an error: a new CA would
        invalidate every certificate already handed out).
    """
    x509, hashes, serialization, ec, EKU, NameOID = _x509()
    folder = Path(folder)
    bad = [n for n in names if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", str(n)) or n == "ca"]
    if bad or not names:
        raise BttsimError(f"bad certificate name(s) {bad or names!r}"[:200] + ": use 1 to 64 letters, digits, '_' and "
                          "'-' (not 'ca')")
    san = _san_entries(x509, hosts)  # checked before anything is written
    if not 0 < days <= MAX_DAYS:
        raise BttsimError(f"--days must be in [1, {MAX_DAYS}], got {days}")
    if (folder / "ca.pem").exists() and not overwrite:
        raise BttsimError(f"{folder / 'ca.pem'} exists: choose another folder (or --force to replace every file)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BttsimError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    san = x509.SubjectAlternativeName(san)
    now = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(minutes=5)  # clock skew between hosts
    until = now + _dt.timedelta(days=int(days))

    def key_pem(key) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    def write(path: Path, data: bytes, private: bool = False) -> None:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
        with os.fdopen(fd, "wb") as f:
            f.write(data)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "bttsim CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(now).not_valid_after(until)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                       content_commitment=False, key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))
    write(folder / "ca.pem", ca.public_bytes(serialization.Encoding.PEM))
    write(folder / "ca-key.pem", key_pem(ca_key), private=True)
    out = {"ca": folder / "ca.pem"}
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
                .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(now).not_valid_after(until)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=True, key_encipherment=False, key_cert_sign=False,
                                             content_commitment=False, data_encipherment=False, key_agreement=False,
                                             crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
                .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
                .add_extension(san, critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
                .sign(ca_key, hashes.SHA256()))
        write(folder / f"{name}.pem", cert.public_bytes(serialization.Encoding.PEM))
        write(folder / f"{name}-key.pem", key_pem(key), private=True)
        out[name] = folder / f"{name}.pem"
    return out
