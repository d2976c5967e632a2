"""The Rerun web viewer page served from our own HTTP server, bound to one address.

Rerun 0.41's ``serve_web_viewer`` listens on every interface (0.0.0.0) and has no bind option.
The page it serves is static: ``index.html``, ``re_viewer.js`` (wasm-bindgen glue) and
``re_viewer_bg.wasm``, plus ``favicon.ico``. The rerun-sdk wheel ships no files for them and
no function returns them; they are embedded, verbatim, in the ``rerun_bindings`` extension
module. :func:`load_assets` finds them there by their own framing -- the page's header
comment and closing tag, the JS glue's first line, the wasm module's magic and section
sizes, the icon directory -- and :class:`WebViewerServer` serves them from a
``http.server`` thread bound to the address asked for (127.0.0.1 by default). The files are
byte-identical to what Rerun's own server sends (a test compares them with
``rerun --serve-web --bind 127.0.0.1``). The page connects to the gRPC server sink, which
binds the same address.
"""

from __future__ import annotations

import importlib.util
import logging
import mmap
import re
import socket
import struct
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

from ..bus.ports import url_host
from ..errors import BttsimError

__all__ = ["WebViewerServer", "find_assets", "load_assets"]

log = logging.getLogger("bttsim.views.web")

_INDEX_START = b"<!doctype html>\n<!-- Rerun SDK-bundled web viewer. -->"
_INDEX_END = b"</html>\n"
_INDEX_TRAILER = re.compile(rb"\n<!--[^\n<>]{0,200}-->\n")  # "Powered by egui" after </html>
_JS_START = b"let wasm_bindgen = (function(exports) {"
_WASM_MAGIC = b"\0asm\x01\0\0\0"
_WASM_CODE_SECTION = 10
_MAX_SECTION_ID = 13

_CONTENT_TYPES = {
    "index.html": "text/html; charset=utf-8",
    "re_viewer.js": "text/javascript",
    "re_viewer_bg.wasm": "application/wasm",
    "favicon.ico": "image/x-icon",
}

_CACHE: dict[str, memoryview] | None = None


def _leb128(data, pos: int) -> tuple[int, int]:
    """Unsigned LEB128 at ``pos``: (value, position after it)."""
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, pos
        if shift > 35:
            raise ValueError("LEB128 too long")


def _wasm_end(data, start: int) -> int:
    """End of the wasm module at ``start``: its sections, walked by their sizes, up to the
    first byte that cannot start one (a module has no length field of its own)."""
    pos, seen_code = start + len(_WASM_MAGIC), False
    while pos < len(data) and data[pos] <= _MAX_SECTION_ID:
        section = data[pos]
        try:
            size, body = _leb128(data, pos + 1)
        except (ValueError, IndexError):
            break
        if body + size > len(data):
            break
        seen_code |= section == _WASM_CODE_SECTION
        pos = body + size
    if not seen_code:
        raise ValueError("the wasm module has no code section")
    return pos


def _ico_end(data, start: int) -> int | None:
    """End of the .ico file at ``start`` (from its directory), or None if none is there."""
    if data[start:start + 4] != b"\0\0\1\0":
        return None
    (count,) = struct.unpack_from("<H", data, start + 4)
    if not 1 <= count <= 64:
        return None
    ends = [struct.unpack_from("<II", data, start + 6 + 16 * i + 8) for i in range(count)]
    end = start + max(offset + size for size, offset in ends)
    return end if end <= len(data) else None


def find_assets(data) -> dict[str, tuple[int, int]]:
    """Where the web viewer's files are in ``data``: ``{name: (start, end)}``.

    Parameters
    ----------
    data : bytes-like
        The extension module's bytes (or any buffer holding the files verbatim).

    Raises
    ------
    ValueError
        A file is not found, or not where the others say it must be.
    """
    out: dict[str, tuple[int, int]] = {}
    start = data.find(_INDEX_START)
    if start < 0:
        raise ValueError("no index.html")
    end = data.find(_INDEX_END, start)
    if end < 0:
        raise ValueError("index.html has no end")
    end += len(_INDEX_END)
    trailer = _INDEX_TRAILER.match(data, end)
    if trailer is not None:
        end = trailer.end()
    out["index.html"] = (start, end)
    ico_end = _ico_end(data, end)
    if ico_end is not None:
        out["favicon.ico"] = (end, ico_end)
    js = data.find(_JS_START, end)
    if js < 0:
        raise ValueError("no re_viewer.js")
    wasm = data.find(_WASM_MAGIC, js)
    if wasm < 0:
        raise ValueError("no re_viewer_bg.wasm")
    glue = bytes(data[js:wasm])
    try:
        text = glue.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("re_viewer.js is not followed by the wasm module") from None
    if not text.rstrip().endswith(";") or "__wbg_init" not in text:
        raise ValueError("re_viewer.js does not end where the wasm module starts")
    out["re_viewer.js"] = (js, wasm)
    out["re_viewer_bg.wasm"] = (wasm, _wasm_end(data, wasm))
    return out


def _extension_module() -> str:
    spec = importlib.util.find_spec("rerun_bindings.rerun_bindings")
    if spec is None or not spec.origin:
        raise BttsimError("cannot serve the web viewer: rerun_bindings is not installed (pip install rerun-sdk)")
    return spec.origin


def load_assets() -> dict[str, memoryview]:
    """The web viewer's files from the installed rerun-sdk (mapped read-only, not copied;
    found once per process).

    Raises
    ------
    BttsimError
        The files are not in the installed rerun-sdk (another version's layout): one line.
    """
    global _CACHE
    if _CACHE is None:
        path = _extension_module()
        try:
            with open(path, "rb") as f:
                data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except OSError as exc:
            raise BttsimError(f"cannot serve the web viewer: {path}: {exc.strerror or exc}") from None
        try:
            where = find_assets(data)
        except ValueError as exc:
            from importlib.metadata import version

            raise BttsimError(f"cannot serve the web viewer: its files are not where expected in rerun-sdk "
                              f"{version('rerun-sdk')} ({exc})") from None
        view = memoryview(data)  # the map lives as long as the process, like the loaded module
        _CACHE = {name: view[a:b] for name, (a, b) in where.items()}
    return _CACHE


class _Handler(BaseHTTPRequestHandler):
    server_version = "bttsim-web"
    protocol_version = "HTTP/1.1"

    def _send(self, head_only: bool) -> None:
        name = urlsplit(self.path).path.lstrip("/") or "index.html"
        body = self.server.assets.get(name)  # type: ignore[attr-defined]
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", _CONTENT_TYPES.get(name, "application/octet-stream"))
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        if not head_only:
            try:
                self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):  # the browser went away
                pass

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        self._send(head_only=False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._send(head_only=True)

    def log_message(self, format, *args) -> None:  # noqa: A002
        log.debug("%s %s", self.address_string(), format % args)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True  # as Rerun's servers: a port in TIME_WAIT is free


class _Server6(_Server):
    address_family = socket.AF_INET6


class WebViewerServer:
    """The web viewer page on ``host:port``, served by a thread until :meth:`close`.

    Parameters
    ----------
    host : str
        IP address to listen on (``127.0.0.1``: this machine only).
    port : int
    assets : dict, optional
        ``{file name: bytes}`` (default :func:`load_assets`).

    Raises
    ------
    BttsimError
        The files cannot be found, or the address cannot be bound (one line).
    """

    def __init__(self, host: str, port: int, assets: dict | None = None) -> None:
        assets = load_assets() if assets is None else assets
        cls = _Server6 if ":" in host else _Server
        try:
            self._httpd = cls((host, int(port)), _Handler)
        except OSError as exc:
            raise BttsimError(f"cannot serve the web viewer on {url_host(host)}:{int(port)}: "
                              f"{(exc.strerror or str(exc)).lower()}") from None
        self._httpd.assets = assets  # type: ignore[attr-defined]
        self.host, self.port = host, self._httpd.server_address[1]
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="bttsim-web-viewer", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{url_host(self.host)}:{self.port}/"

    def close(self) -> None:
        """Stop serving and release the port (idempotent)."""
        if self._thread.is_alive():
            self._httpd.shutdown()
            self._thread.join()
        self._httpd.server_close()
