"""User-visible defaults that several layers share, in one place (no dependencies).

All servers bind to loopback (127.0.0.1) by default; the web viewer's ``--bind`` chooses another
address on purpose.
"""

__all__ = ["DEFAULT_WEB_PORT", "DEFAULT_GRPC_PORT", "DEFAULT_BIND", "DEFAULT_RIG"]

#: HTTP port of the Rerun web viewer (``--web``).
DEFAULT_WEB_PORT = 9090
#: Port of the Rerun gRPC data server that the web viewer connects to.
DEFAULT_GRPC_PORT = 9876
#: Address the web viewer's two servers (page and data) listen on (``--bind``).
DEFAULT_BIND = "127.0.0.1"
#: Rig name of the default scenario (keys ``bttsim/<rig>/...``).
DEFAULT_RIG = "rig1"
