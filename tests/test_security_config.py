"""The security configuration in-process: certificates, the access-control policy, the Zenoh config."""

import json

import pytest

from bttsim_stream.bus.certs import IDENTITIES, generate_certificates
from bttsim_stream.bus.security import TRUTH_READERS, TlsFiles, access_control_policy
from bttsim_stream.bus.session import make_config
from bttsim_stream.errors import BttsimError


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    d = tmp_path_factory.mktemp("certs")
    generate_certificates(d, IDENTITIES, hosts=("10.0.0.2", "router.lab"))
    return d


def test_certificates_name_their_identity_and_chain_to_the_ca(certs):
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    ca = x509.load_pem_x509_certificate((certs / "ca.pem").read_bytes())
    for name in IDENTITIES:
        cert = x509.load_pem_x509_certificate((certs / f"{name}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert {"localhost", "router.lab"} <= set(san.get_values_for_type(x509.DNSName))
        assert {"127.0.0.1", "10.0.0.2"} <= {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}


def test_policy_is_default_deny_and_names_only_what_it_defines():
    acl = access_control_policy()
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])  # no deny rules: no precedence questions
    rules = {r["id"] for r in acl["rules"]}
    subjects = {s["id"] for s in acl["subjects"]}
    assert subjects == set(IDENTITIES)
    for p in acl["policies"]:
        assert set(p["rules"]) <= rules and set(p["subjects"]) <= subjects, p

    def who(rule_id):
        return {s for p in acl["policies"] if rule_id in p["rules"] for s in p["subjects"]}

    assert who("publish acquisition") == {"sim", "router"}
    assert who("publish results") == {"processor", "router"}
    assert who("receive truth") == set(TRUTH_READERS) == {"processor", "recorder", "viewer", "router"}
    by_id = {r["id"]: r for r in acl["rules"]}
    assert by_id["publish acquisition"]["flows"] == ["ingress"]
    assert "bttsim/*/truth" in by_id["publish acquisition"]["key_exprs"]
    assert "bttsim/*/signal/*" in by_id["publish acquisition"]["key_exprs"]  # raw signals: acquisition data
    assert "bttsim/*/signal/*" in by_id["receive data"]["key_exprs"]
    assert "bttsim/*/truth" not in by_id["receive data"]["key_exprs"]
    assert by_id["tokens of sim"]["key_exprs"] == ["bttsim/*/*/sim"] and who("tokens of sim") == {"sim"}


def test_make_config_with_tls_and_the_defaults_without(certs):
    tls = TlsFiles(certs / "ca.pem", certs / "processor.pem", certs / "processor-key.pem")
    conf = make_config("client", connect=["tls/127.0.0.1:7447"], tls=tls, connect_timeout_s=5)
    section = json.loads(conf.get_json("transport/link/tls"))
    assert section["enable_mtls"] is True and section["connect_certificate"].endswith("processor.pem")
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    assert json.loads(conf.get_json("connect/timeout_ms"))["client"] == 5000
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    plain = make_config(listen=["tcp/127.0.0.1:7447"])  # security off: as before
    assert json.loads(plain.get_json("access_control/enabled")) in (None, False)
    assert json.loads(plain.get_json("transport/link/tls/enable_mtls")) is None
    assert json.loads(plain.get_json("connect/timeout_ms")) is None  # nothing to connect to
    no_acl = make_config(listen=["tls/127.0.0.1:7447"], tls=TlsFiles(tls.ca, tls.cert, tls.key, False))
    assert json.loads(no_acl.get_json("access_control/enabled")) in (None, False)


@pytest.mark.parametrize("kwargs, words", [
    ({"listen": ["tcp/127.0.0.1:7447"], "tls": True}, "must be tls/"),
    ({"connect": ["tcp/127.0.0.1:7447"], "connect_timeout_s": 0}, "must be positive"),
], ids=["plain-endpoint-with-tls", "zero-timeout"])
def test_make_config_refuses(certs, kwargs, words):
    if kwargs.get("tls"):
        kwargs["tls"] = TlsFiles(certs / "ca.pem", certs / "sim.pem", certs / "sim-key.pem")
    with pytest.raises(BttsimError, match=words):
        make_config(**kwargs)


def test_missing_certificate_file_is_one_line(tmp_path):
    with pytest.raises(BttsimError, match="no such CA certificate file"):
        TlsFiles(tmp_path / "ca.pem", tmp_path / "x.pem", tmp_path / "x-key.pem")


def test_a_file_that_is_no_pem_is_refused_as_a_certificate(certs, tmp_path):
    """A text file given as the CA, certificate or key is one line, before any session (the
    node used to start with it, TLS never tried)."""
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    for files, what in [((text, certs / "sim.pem", certs / "sim-key.pem"), "not a PEM CA certificate"),
                        ((certs / "ca.pem", text, certs / "sim-key.pem"), "not a PEM certificate"),
                        ((certs / "ca.pem", certs / "sim.pem", text), "not a PEM private key")]:
        with pytest.raises(BttsimError, match=what):
            TlsFiles(*files)
    TlsFiles(certs / "ca.pem", certs / "sim.pem", certs / "sim-key.pem")  # the real ones load
