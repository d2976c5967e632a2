"""Where the views go: an ``.rrd`` file, a running viewer, and/or a web viewer served from here.

Ports default to :data:`~bttsim_stream.defaults.DEFAULT_WEB_PORT` and
:data:`~bttsim_stream.defaults.DEFAULT_GRPC_PORT`, the address to
:data:`~bttsim_stream.defaults.DEFAULT_BIND` (127.0.0.1). Both servers of the web viewer
listen on that one address: the gRPC data server (Rerun's server sink) and the page
(:mod:`.webviewer`, our own server: Rerun 0.41's ``serve_web_viewer`` binds every interface).
"""

from __future__ import annotations

import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

from ..bus.ports import check_web_ports, url_host
from ..defaults import DEFAULT_BIND, DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from ..errors import BttsimError
from .webviewer import WebViewerServer

__all__ = ["APPLICATION_ID", "ViewSinks", "finish_files", "open_recording"]

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
    web_server : WebViewerServer or None
        The page's server (stopped by :meth:`close`).
    """

    rrd_path: str | None = None
    grpc_url: str | None = None
    server_url: str | None = None
    web_url: str | None = None
    web_server: WebViewerServer | None = field(default=None, repr=False)

    def close(self) -> None:
        """Stop serving the web viewer page (the stream's ``disconnect`` stops the data server)."""
        if self.web_server is not None:
            self.web_server.close()


def open_recording(*, rrd_path=None, grpc_url: str | None = None, serve_web: bool = False,
                   web_port: int = DEFAULT_WEB_PORT, grpc_port: int = DEFAULT_GRPC_PORT,
                   bind: str = DEFAULT_BIND, blueprint: rrb.Blueprint | None = None, recording_id: str | None = None,
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
        Host a gRPC server on ``bind:grpc_port`` and the web viewer page on ``bind:web_port``.
        Both stop with the process (the data server when the stream is disconnected, the
        page with ``sinks.close()``).
    web_port, grpc_port : int
    bind : str
        IP address both servers listen on (127.0.0.1: this machine only).
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
        No sink requested, a bad address, or a port in use (one line).
    """
    if not (rrd_path or grpc_url or serve_web):
        raise BttsimError("no Rerun output: give an .rrd file, a viewer URL or the web viewer")
    if serve_web:
        bind = check_web_ports(bind, web_port, grpc_port)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    sinks: list = []
    server_url = web_url = web_server = None
    if rrd_path:
        if Path(rrd_path).is_dir():
            raise BttsimError(f"{rrd_path}: is a folder (give the .rrd file's path)")
        Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
        open(rrd_path, "wb").close()  # a file that cannot be written is an error before anything is logged
        sinks.append(_sink(rr.FileSink, str(rrd_path)))
    if grpc_url:
        sinks.append(_sink(rr.GrpcSink, grpc_url))
    if serve_web:
        # Rerun joins "ip:port" as given: an IPv6 address needs its brackets
        server = rr.GrpcServerSink(f"[{bind}]" if ":" in bind else bind, int(grpc_port),
                                   server_memory_limit=server_memory_limit)
        server_url = f"rerun+http://{url_host(bind)}:{int(grpc_port)}/proxy"
        sinks.append(server)
    try:
        rec.set_sinks(*sinks, default_blueprint=blueprint)
    except RuntimeError as exc:  # the file sink opens its file here
        raise BttsimError(f"{rrd_path or grpc_url}: {' '.join(str(exc).split())[:200]}") from None
    if serve_web:
        try:
            web_server = WebViewerServer(bind, int(web_port))
        except BttsimError:
            rec.disconnect()
            raise
        web_url = f"{web_server.url}?url={urllib.parse.quote(server_url, safe='')}"
    return rec, ViewSinks(rrd_path=str(rrd_path) if rrd_path else None, grpc_url=grpc_url,
                          server_url=server_url, web_url=web_url, web_server=web_server)


def _sink(kind, where: str):
    """A Rerun sink of ``kind`` to ``where``; what Rerun refuses (a URL that is not one) is
    one line."""
    try:
        return kind(where)
    except (RuntimeError, ValueError) as exc:
        raise BttsimError(f"{where}: {' '.join(str(exc).split())[:200]}") from None


def finish_files(rec: rr.RecordingStream) -> None:
    """Finalise the stream's ``.rrd`` file (its footer) and keep its servers running: a
    viewer that keeps serving after the run leaves a complete file behind at once."""
    import rerun_bindings

    rec.flush()
    rerun_bindings.finalize_deferred_sinks(recording=rec.to_native())
