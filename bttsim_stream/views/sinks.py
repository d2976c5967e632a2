"""Where the views go: an ``.rrd`` file, a running viewer, and/or a web viewer served from here.

Ports default to :data:`~bttsim_stream.defaults.DEFAULT_WEB_PORT` and
:data:`~bttsim_stream.defaults.DEFAULT_GRPC_PORT`. The data server binds to 127.0.0.1;
Rerun 0.41's ``serve_web_viewer`` has no bind option, so the (static) web page server
listens on every interface.
"""

from __future__ import annotations

import socket
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

from ..defaults import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from ..errors import BttsimError

__all__ = ["APPLICATION_ID", "ViewSinks", "open_recording"]

#: Rerun application id of every bttsim recording (blueprints are stored per application).
APPLICATION_ID = "bttsim"


@dataclass(frozen=True, slots=True)
class ViewSinks:
    """Where a recording stream goes.

    Attributes
    ----------
    rrd_path : str or None
        Offline ``.rrd`` file (open it with ``rerun FILE.rrd``).
    grpc_url : str or None
        A running viewer the stream connects to.
    server_url : str or None
        The gRPC server hosted by this process (``serve_web``), e.g.
        ``rerun+http://127.0.0.1:9876/proxy``.
    web_url : str or None
        The web viewer page, connected to ``server_url``.
    """

    rrd_path: str | None = None
    grpc_url: str | None = None
    server_url: str | None = None
    web_url: str | None = None


def open_recording(*, rrd_path=None, grpc_url: str | None = None, serve_web: bool = False,
                   web_port: int = DEFAULT_WEB_PORT, grpc_port: int = DEFAULT_GRPC_PORT,
                   blueprint: rrb.Blueprint | None = None, recording_id: str | None = None,
                   server_memory_limit: str = "512MiB") -> tuple[rr.RecordingStream, ViewSinks]:
    """A Rerun recording stream teed to the requested sinks.

    Parameters
    ----------
    rrd_path : path, optional
        Write an ``.rrd`` file (with a footer, so ``rerun rrd verify`` accepts it once the
        stream is disconnected).
    grpc_url : str, optional
        Connect to a running viewer, e.g. ``rerun+http://127.0.0.1:9876/proxy``.
    serve_web : bool
        Host a gRPC server on ``127.0.0.1:grpc_port`` and the web viewer on ``web_port``.
        Both stop with the process (and the server when the stream is disconnected).
    web_port, grpc_port : int
    blueprint : Blueprint, optional
        Default blueprint (else send one later with ``send_blueprint``).
    recording_id : str, optional
        E.g. the run id, so that re-logging the same run replaces it in a viewer.
    server_memory_limit : str
        What the hosted gRPC server keeps for viewers that connect late.

    Returns
    -------
    rec : rerun.RecordingStream
    sinks : ViewSinks

    Raises
    ------
    BttsimError
        No sink requested, or a port in use (one line).
    """
    if not (rrd_path or grpc_url or serve_web):
        raise BttsimError("no Rerun output: give an .rrd file, a viewer URL or the web viewer")
    if serve_web:
        for port, what in ((grpc_port, "gRPC"), (web_port, "web viewer")):
            _check_port_free(int(port), what)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    sinks: list = []
    server_url = web_url = None
    if rrd_path:
        Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd_path)))
    if grpc_url:
        sinks.append(rr.GrpcSink(grpc_url))
    if serve_web:
        server = rr.GrpcServerSink("127.0.0.1", int(grpc_port), server_memory_limit=server_memory_limit)
        server_url = server.uri
        sinks.append(server)
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    if serve_web:
        try:
            rr.serve_web_viewer(web_port=int(web_port), open_browser=False, connect_to=server_url)
        except RuntimeError as exc:
            rec.disconnect()
            raise BttsimError(f"cannot serve the web viewer: {' '.join(str(exc).split())}") from None
        web_url = f"http://127.0.0.1:{int(web_port)}/?url={urllib.parse.quote(server_url, safe='')}"
    return rec, ViewSinks(rrd_path=str(rrd_path) if rrd_path else None, grpc_url=grpc_url,
                          server_url=server_url, web_url=web_url)


def _check_port_free(port: int, what: str) -> None:
    """Rerun reports a busy server port only in its log: check first (one-line error)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the servers do: TIME_WAIT is fine
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            raise BttsimError(f"cannot serve the {what} on port {port}: address in use") from None
