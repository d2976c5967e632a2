"""Router node: a Zenoh router for multi-host layouts (no ``zenohd`` ships on the registries).

Nodes on other hosts connect to it in client mode (``-m client -e tcp/ROUTER_HOST:7447``) and
it routes every ``bttsim/**`` key between them; peers behind a router exchange nothing, so use
client mode. Listens on ``-l`` (default ``tcp/127.0.0.1:7447``, or ``tls/127.0.0.1:7447``
with ``--tls-dir``: loopback; give the host's address to serve other hosts), connects to other
routers with ``-e``. With ``--tls-dir`` it uses the ``router`` identity and enforces the
access-control policy on every client's link (``docs/security.md``). Liveliness:
``bttsim/<rig>/alive/router``. Runs until ``--duration``, SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import sys

from bttsim_stream.bus import keys
from bttsim_stream.defaults import DEFAULT_RIG
from bttsim_stream.bus.session import StopFlag, config_from_args, opened
from bttsim_stream.bus.security import tls_from_args
from bttsim_stream.runtime import NodeProgram, add_duration_argument, run_node

log = logging.getLogger("bttsim.router")
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def main(conf, args: argparse.Namespace) -> None:
    """Route until stopped. ``conf`` is rebuilt in router mode from the same flags."""
    rig = keys.validate_rig(args.rig)
    default = DEFAULT_LISTEN if tls_from_args(args, "router") is None else DEFAULT_LISTEN.replace("tcp/", "tls/")
    listen = args.listen or [default]
    conf = config_from_args(args, mode="router", listen=listen)
    stop = StopFlag(args.duration)
    with opened(conf) as session:
        token = session.liveliness().declare_token(keys.alive_key(rig, "router"))
        log.info("routing on %s", ", ".join(listen))
        print("router ready", flush=True)
        while not stop.wait(0.5):
            pass
        token.undeclare()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default=DEFAULT_RIG, help=f"rig whose liveliness the router announces ({DEFAULT_RIG})")
    add_duration_argument(p)


PROGRAM = NodeProgram("router", __doc__, add_arguments, main)


def run(argv=None) -> int:
    return run_node(PROGRAM, argv)


if __name__ == "__main__":
    sys.exit(run())
