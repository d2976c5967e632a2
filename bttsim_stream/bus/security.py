"""Security you can switch on: mutual TLS between every node and Zenoh access control.

Off by default. With a certificate folder (``--tls-dir DIR``, made by ``bttsim certs DIR``) or
explicit files (``--tls-ca``, ``--tls-cert``, ``--tls-key``), a node speaks only TLS with
mutual authentication (``tls/HOST:PORT`` endpoints; a peer without a certificate signed by
the same CA is refused during the handshake) and enforces the access-control policy of
:func:`access_control_policy` on every link. Identities are certificate common names
(:data:`~bttsim_stream.bus.certs.IDENTITIES`):

==========================  =====================================  ===========================
who                         may publish (put, reply)               may receive
==========================  =====================================  ===========================
``sim``                     ``opr``, ``toa/*``, ``signal/*``,      everything but ``truth``
                            ``meta``, ``truth``
``processor``               ``fit``, ``tw/*``, ``resonance``       everything
``recorder``, ``viewer``    nothing                                everything
``run``                     nothing                                everything but ``truth``
``router``                  everything (it relays)                 everything
any other name / no cert    refused (default: deny)                nothing
==========================  =====================================  ===========================

Every member may subscribe, query, declare queryables and follow liveliness under
``bttsim/**``; each declares only its own liveliness tokens (``bttsim/<rig>/<what>/<name>``:
``alive``, ``ready``...) and publishes only its own status (``bttsim/<rig>/status/<name>``,
which every member may receive), so nobody can pose as the simulator and end a run early, nor
report another node's statistics. Each node checks what comes in from (ingress) and goes out
to (egress) each neighbour: with a router, the router is the neighbour of every client, and it
enforces the policy on the clients' links.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import BttsimError
from .certs import IDENTITIES

__all__ = ["TlsFiles", "add_security_args", "tls_from_args", "access_control_policy", "apply_security",
           "security_config", "write_config_files", "TRUTH_READERS"]

#: Identities allowed to receive ``bttsim/<rig>/truth`` (the router relays it).
TRUTH_READERS = ("processor", "recorder", "viewer", "router")

_ACQ = ["bttsim/*/opr", "bttsim/*/toa/*", "bttsim/*/signal/*", "bttsim/*/meta"]
_TRUTH = ["bttsim/*/truth"]
_RESULTS = ["bttsim/*/fit", "bttsim/*/tw/*", "bttsim/*/resonance"]
_STATUS = ["bttsim/*/status/*"]
# zenoh-ext's advanced publishers and subscribers use keys under a verbatim chunk ``@adv``
# (liveliness tokens, cache queries), which ``**`` does not match
_CONTROL = ["bttsim/**", "bttsim/**/@adv/**"]
_DECLARE = ["declare_subscriber", "query", "declare_queryable", "declare_liveliness_subscriber", "liveliness_query"]
_DATA = ["put", "reply"]


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """The TLS material of one node (PEM files) and whether access control is on.

    Attributes
    ----------
    ca : Path
        Certificate of the CA that signed every node's certificate (``ca.pem``).
    cert, key : Path
        This node's certificate and private key; the certificate's common name is its identity.
    access_control : bool
        Enforce :func:`access_control_policy` (default True).
    """

    ca: Path
    cert: Path
    key: Path
    access_control: bool = True

    def __post_init__(self) -> None:
        for what, p in (("CA certificate", self.ca), ("certificate", self.cert), ("private key", self.key)):
            if not Path(p).is_file():
                raise BttsimError(f"{p}: no such {what} file (make them with: bttsim certs DIR)")
            with open(p, "rb") as f:
                if b"-----BEGIN " not in f.read(1 << 16):
                    raise BttsimError(f"{p}: not a PEM {what} (make them with: bttsim certs DIR)")


def add_security_args(parser: argparse.ArgumentParser) -> None:
    """``--tls-dir``, ``--tls-name``, ``--tls-ca``, ``--tls-cert``, ``--tls-key``, ``--no-access-control``."""
    g = parser.add_argument_group("security (off unless a certificate is given; see docs/security.md)")
    g.add_argument("--tls-dir", metavar="DIR",
                   help="mutual TLS and access control with DIR/ca.pem, DIR/NAME.pem, DIR/NAME-key.pem "
                        "(bttsim certs DIR makes them); endpoints must then be tls/HOST:PORT")
    g.add_argument("--tls-name", metavar="NAME",
                   help="identity (certificate name) to use from --tls-dir (default: the node's name)")
    g.add_argument("--tls-ca", metavar="PEM", help="CA certificate (instead of --tls-dir)")
    g.add_argument("--tls-cert", metavar="PEM", help="this node's certificate (instead of --tls-dir)")
    g.add_argument("--tls-key", metavar="PEM", help="this node's private key (instead of --tls-dir)")
    g.add_argument("--no-access-control", action="store_true",
                   help="with TLS, authenticate only (no per-identity access control)")


def tls_from_args(args: argparse.Namespace, default_name: str) -> TlsFiles | None:
    """The :class:`TlsFiles` the security flags ask for (None: security off)."""
    files = (getattr(args, "tls_ca", None), getattr(args, "tls_cert", None), getattr(args, "tls_key", None))
    folder = getattr(args, "tls_dir", None)
    acl = not getattr(args, "no_access_control", False)
    if folder and any(files):
        raise BttsimError("give either --tls-dir or --tls-ca/--tls-cert/--tls-key, not both")
    if folder:
        name = getattr(args, "tls_name", None) or default_name
        d = Path(folder)
        return TlsFiles(d / "ca.pem", d / f"{name}.pem", d / f"{name}-key.pem", acl)
    if any(files):
        if not all(files):
            raise BttsimError("--tls-ca, --tls-cert and --tls-key go together")
        return TlsFiles(Path(files[0]), Path(files[1]), Path(files[2]), acl)
    if getattr(args, "tls_name", None) or getattr(args, "no_access_control", False):
        raise BttsimError("--tls-name and --no-access-control need --tls-dir (or --tls-ca/--tls-cert/--tls-key)")
    return None


def access_control_policy(identities=IDENTITIES) -> dict:
    """The ``access_control`` section of a node's Zenoh configuration (see the module table).

    Default deny; allow rules only, one set per direction: *ingress* rules say what a
    neighbour may send, *egress* rules what it may receive.
    """
    members = [n for n in identities]
    readers = [n for n in members if n in TRUTH_READERS]
    rules = [
        {"id": "declare", "permission": "allow", "flows": ["ingress", "egress"], "messages": _DECLARE,
         "key_exprs": _CONTROL},
        {"id": "see tokens", "permission": "allow", "flows": ["egress"], "messages": ["liveliness_token"],
         "key_exprs": _CONTROL},
        {"id": "internal tokens", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
         "key_exprs": ["bttsim/**/@adv/**"]},
        {"id": "receive data", "permission": "allow", "flows": ["egress"], "messages": _DATA,
         "key_exprs": _ACQ + _RESULTS + _STATUS},
        {"id": "receive truth", "permission": "allow", "flows": ["egress"], "messages": _DATA, "key_exprs": _TRUTH},
        {"id": "publish acquisition", "permission": "allow", "flows": ["ingress"], "messages": _DATA,
         "key_exprs": _ACQ + _TRUTH},
        {"id": "publish results", "permission": "allow", "flows": ["ingress"], "messages": _DATA,
         "key_exprs": _RESULTS},
        {"id": "relay tokens", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
         "key_exprs": _CONTROL},
        {"id": "relay status", "permission": "allow", "flows": ["ingress"], "messages": _DATA, "key_exprs": _STATUS},
    ]
    policies = [
        {"id": "members", "rules": ["declare", "see tokens", "internal tokens", "receive data"], "subjects": members},
        {"id": "truth readers", "rules": ["receive truth"], "subjects": readers},
        {"id": "simulator", "rules": ["publish acquisition"],
         "subjects": [n for n in ("sim", "router") if n in members]},
        {"id": "processor", "rules": ["publish results"],
         "subjects": [n for n in ("processor", "router") if n in members]},
        {"id": "router", "rules": ["relay tokens", "relay status"],
         "subjects": [n for n in ("router",) if n in members]},
    ]
    for n in members:  # each one's own liveliness tokens (alive, ready, done...) and status
        rules.append({"id": f"tokens of {n}", "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": [f"bttsim/*/*/{n}"]})
        rules.append({"id": f"status of {n}", "permission": "allow", "flows": ["ingress"],
                      "messages": _DATA, "key_exprs": [f"bttsim/*/status/{n}"]})
        policies.append({"id": f"own tokens of {n}", "rules": [f"tokens of {n}", f"status of {n}"], "subjects": [n]})
    policies = [p for p in policies if p["subjects"]]
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": [{"id": n, "cert_common_names": [n]} for n in members], "policies": policies}


def tls_section(tls: TlsFiles) -> dict:
    """The ``transport/link/tls`` section: the same certificate to listen and to connect, the
    peer's certificate required (mutual TLS) and checked against the CA."""
    ca, cert, key = (str(Path(p).resolve()) for p in (tls.ca, tls.cert, tls.key))
    return {"root_ca_certificate": ca, "enable_mtls": True,
            "listen_certificate": cert, "listen_private_key": key,
            "connect_certificate": cert, "connect_private_key": key,
            "verify_name_on_connect": True}


def security_config(tls: TlsFiles) -> dict:
    """The sections the security flags add to a node's Zenoh configuration (a dict to dump as
    JSON / JSON5): ``transport/link/tls`` and, unless switched off, ``access_control``."""
    out: dict = {"transport": {"link": {"tls": tls_section(tls)}}}
    if tls.access_control:
        out["access_control"] = access_control_policy()
    return out


def apply_security(conf, tls: TlsFiles) -> None:
    """Insert TLS (and, unless switched off, access control) into a ``zenoh.Config``."""
    sections = security_config(tls)
    conf.insert_json5("transport/link/tls", json.dumps(sections["transport"]["link"]["tls"]))
    if "access_control" in sections:
        conf.insert_json5("access_control", json.dumps(sections["access_control"]))


def write_config_files(folder, names) -> list[Path]:
    """``folder/NAME.json5`` for every name with a certificate there: a Zenoh configuration
    with the security sections of that identity (``-c FILE`` is then the same as
    ``--tls-dir folder --tls-name NAME``; add mode and endpoints to it or on the command line)."""
    folder = Path(folder)
    out = []
    for name in names:
        tls = TlsFiles(folder / "ca.pem", folder / f"{name}.pem", folder / f"{name}-key.pem")
        path = folder / f"{name}.json5"
        path.write_text(f"// bttsim: mutual TLS and access control of identity {name!r} (docs/security.md)\n"
                        + json.dumps(security_config(tls), indent=2) + "\n")
        out.append(path)
    return out
