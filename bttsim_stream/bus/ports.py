"""Listening addresses of the web viewer's servers: ``--bind`` parsing and a port check that
fails as one line before anything starts (Rerun reports a busy port only in its log)."""

from __future__ import annotations

import ipaddress
import socket

from ..errors import BttsimError

__all__ = ["parse_bind", "check_port_free", "check_web_ports", "url_host"]


def parse_bind(addr: str) -> str:
    """The IP address ``addr`` (``--bind``), normalised; BttsimError if it is not one.

    Host names are refused on purpose: what a name resolves to (and so which interface
    serves) must not depend on the resolver.
    """
    try:
        return str(ipaddress.ip_address(str(addr).strip().strip("[]")))
    except ValueError:
        raise BttsimError(f"--bind {addr!r}: not an IP address (e.g. 127.0.0.1 or ::1)") from None


def check_port_free(host: str, port: int, what: str) -> None:
    """Raise a one-line BttsimError unless TCP ``port`` can be bound on ``host``.

    Bound as the servers bind (``SO_REUSEADDR``: a port in TIME_WAIT is free). On Linux this
    also fails when another socket listens on the wildcard address with the same port.
    """
    port = int(port)
    if not 1 <= port <= 65535:
        raise BttsimError(f"{what} port {port}: must be in 1..65535")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise BttsimError(f"cannot serve the {what} on {url_host(host)}:{port}: "
                              f"{(exc.strerror or str(exc)).lower()}") from None


def check_web_ports(bind: str, web_port: int, grpc_port: int) -> str:
    """Check the web viewer's two servers can listen (``--bind``, ``--web-port``,
    ``--grpc-port``) before any work starts; the normalised bind address. One-line
    BttsimError for a bad address, equal ports or a port in use."""
    bind = parse_bind(bind)
    if int(web_port) == int(grpc_port):
        raise BttsimError(f"--web-port and --grpc-port are both {int(web_port)}: give two ports")
    check_port_free(bind, int(grpc_port), "web viewer's data server (--grpc-port)")
    check_port_free(bind, int(web_port), "web viewer (--web-port)")
    return bind


def url_host(host: str) -> str:
    """``host`` as it goes in a URL: IPv6 in brackets; a wildcard address (every interface)
    becomes the loopback address of its family, which reaches it from this machine."""
    if host in ("0.0.0.0", ""):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host
