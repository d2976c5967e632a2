"""The web viewer page from our own server: its files found in rerun-sdk by their framing,
served on one address (loopback by default), ports checked before anything starts."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import textwrap
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from _net import can_connect, is_loopback, listening, listening_of
from bttsim_stream.bus.ports import check_port_free, parse_bind, url_host
from bttsim_stream.bus.session import free_port
from bttsim_stream.errors import BttsimError

pytest.importorskip("rerun")
from bttsim_stream.views import webviewer  # noqa: E402
from bttsim_stream.views.sinks import open_recording  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

# --------------------------------------------------------------------------------------
# Finding the files (exact fixture: a made-up module holding them at known offsets)
# --------------------------------------------------------------------------------------

INDEX = (b"<!doctype html>\n<!-- Rerun SDK-bundled web viewer. -->\n<html><body>"
         b"<script src=\"re_viewer.js\"></script></body>\n</html>\n\n<!-- Powered by egui -->\n")
ICON_DATA = b"\x89PNG fake icon"
ICO = struct.pack("<HHH", 0, 1, 1) + struct.pack("<BBBBHHII", 16, 16, 0, 0, 1, 32, len(ICON_DATA), 22) + ICON_DATA
JS = b"let wasm_bindgen = (function(exports) {\n    async function __wbg_init() {}\n})({ __proto__: null });\n"
WASM = (b"\0asm\x01\0\0\0"
        b"\x01\x04\x01\x60\x00\x00"  # type section: one () -> () signature
        b"\x03\x02\x01\x00"  # function section: one function of type 0
        b"\x0a\x04\x01\x02\x00\x0b"  # code section: one body (no locals, end)
        b"\x00\x07\x04name\x00\x00")  # a custom section (as the real module ends with)
AFTER = b"<!doctype html>\n<html>signed in</html>\n"


def _blob() -> tuple[bytes, dict[str, bytes]]:
    parts = [b"\x7fELF" + bytes(range(256)) * 3, INDEX, ICO, b"sw.js: self.addEventListener();\n", JS, WASM, AFTER,
             b"\xcc" * 100]
    # the service worker sits between the icon and the glue in Rerun's module: not served
    return b"".join(parts), {"index.html": INDEX, "favicon.ico": ICO, "re_viewer.js": JS, "re_viewer_bg.wasm": WASM}


def test_find_assets_returns_each_file_exactly():
    blob, files = _blob()
    where = webviewer.find_assets(blob)
    assert set(where) == set(files)
    for name, (a, b) in where.items():
        assert blob[a:b] == files[name], name


def test_find_assets_needs_the_glue_right_before_the_module():
    blob, _ = _blob()
    with pytest.raises(ValueError, match="re_viewer.js"):
        webviewer.find_assets(blob.replace(b"})({ __proto__: null });\n", b"\xff\xfe binary"))
    with pytest.raises(ValueError, match="index.html"):
        webviewer.find_assets(blob.replace(b"Rerun SDK-bundled", b"Some other"))
    with pytest.raises(ValueError, match="code section"):
        webviewer.find_assets(blob.replace(b"\x0a\x04\x01\x02\x00\x0b", b"\x0b\x04\x01\x02\x00\x0b"))


def test_the_installed_rerun_sdk_holds_the_files():
    assets = webviewer.load_assets()
    assert set(assets) >= {"index.html", "re_viewer.js", "re_viewer_bg.wasm"}
    index = bytes(assets["index.html"])
    assert index.startswith(b"<!doctype html>") and index.rstrip().endswith(b"-->")
    assert b'<script src="re_viewer.js">' in index and b'fetch("./re_viewer_bg.wasm")' in index
    assert bytes(assets["re_viewer.js"]).startswith(b"let wasm_bindgen")
    assert bytes(assets["re_viewer_bg.wasm"][:8]) == b"\0asm\x01\0\0\0" and len(assets["re_viewer_bg.wasm"]) > 10e6


_FETCH_FROM_RERUN = textwrap.dedent("""
    import sys, urllib.request
    import rerun as rr
    from bttsim_stream.views.webviewer import load_assets
    port = int(sys.argv[1])
    rr.serve_web_viewer(web_port=port, open_browser=False)
    for name, body in sorted(load_assets().items()):
        theirs = urllib.request.urlopen(f"http://127.0.0.1:{port}/{name}", timeout=120).read()
        print(name, len(theirs), bytes(body) == theirs)
""")


@pytest.mark.integration
def test_the_files_are_byte_identical_to_what_rerun_serves():
    """Rerun's own server (it binds every interface: run it in a loopback-only network
    namespace) sends exactly the bytes we found."""
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-n", "true"], capture_output=True).returncode:
        pytest.skip("needs 'unshare -n' (Rerun's server binds every interface: only in a private namespace)")
    res = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up && exec \"$@\"", "sh", sys.executable,
                          "-c", _FETCH_FROM_RERUN, str(free_port())], cwd=REPO, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = res.stdout.split("\n")
    assert len([ln for ln in lines if ln]) == len(webviewer.load_assets()), res.stdout
    assert all(ln.endswith(" True") for ln in lines if ln), res.stdout


# --------------------------------------------------------------------------------------
# The server
# --------------------------------------------------------------------------------------


def _get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=60) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, "", b""


def test_server_serves_the_page_on_loopback_only():
    _, files = _blob()
    port = free_port()
    server = webviewer.WebViewerServer("127.0.0.1", port, assets=files)
    try:
        assert ("127.0.0.1", port) in listening_of([os.getpid()])
        assert not [s for s in listening_of([os.getpid()]) if s[1] == port and not is_loopback(s[0])]
        status, ctype, body = _get(f"http://127.0.0.1:{port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A1%2Fproxy")
        assert (status, body) == (200, INDEX) and ctype.startswith("text/html")
        assert _get(f"http://127.0.0.1:{port}/re_viewer_bg.wasm")[:3] == (200, "application/wasm", WASM)
        assert _get(f"http://127.0.0.1:{port}/re_viewer.js")[:3] == (200, "text/javascript", JS)
        assert _get(f"http://127.0.0.1:{port}/../../etc/passwd")[0] == 404
        assert _get(f"http://127.0.0.1:{port}/sw.js")[0] == 404
    finally:
        server.close()
    assert not can_connect("127.0.0.1", port)
    check_port_free("127.0.0.1", port, "again")  # released
    server.close()  # idempotent


def test_server_on_a_busy_port_is_one_line():
    port = free_port()
    first = webviewer.WebViewerServer("127.0.0.1", port, assets={})
    try:
        with pytest.raises(BttsimError,
                           match=f"cannot serve the web viewer on 127.0.0.1:{port}: address already in use"):
            webviewer.WebViewerServer("127.0.0.1", port, assets={})
    finally:
        first.close()


def test_open_recording_serves_both_servers_on_the_bind_address(tmp_path):
    web_port, grpc_port = free_port(), free_port()
    rec, sinks = open_recording(serve_web=True, web_port=web_port, grpc_port=grpc_port)
    try:
        mine = listening_of([os.getpid()])
        assert ("127.0.0.1", web_port) in mine and ("127.0.0.1", grpc_port) in mine
        assert all(is_loopback(addr) for addr, port in mine if port in (web_port, grpc_port)), mine
        assert sinks.web_url == (f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A"
                                 f"{grpc_port}%2Fproxy")
        assert sinks.server_url == f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        status, _, body = _get(sinks.web_url)
        assert status == 200 and b"Rerun SDK-bundled web viewer" in body
    finally:
        rec.disconnect()
        sinks.close()
    assert not can_connect("127.0.0.1", web_port)


def test_open_recording_bind_ipv6_loopback():
    if not any(addr == "::1" for addr, _, _ in listening()) and not _has_ipv6_loopback():
        pytest.skip("no IPv6 loopback here")
    web_port, grpc_port = free_port(), free_port()
    rec, sinks = open_recording(serve_web=True, web_port=web_port, grpc_port=grpc_port, bind="::1")
    try:
        mine = listening_of([os.getpid()])
        assert ("::1", web_port) in mine and ("::1", grpc_port) in mine, mine
        assert sinks.web_url.startswith(f"http://[::1]:{web_port}/?url=rerun%2Bhttp%3A%2F%2F%5B%3A%3A1%5D")
        assert _get(f"http://[::1]:{web_port}/")[0] == 200
    finally:
        rec.disconnect()
        sinks.close()


def _has_ipv6_loopback() -> bool:
    import socket

    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


@pytest.mark.parametrize("which", ["web", "grpc"], ids=["web port busy", "grpc port busy"])
def test_open_recording_with_a_busy_port_is_one_line_and_serves_nothing(which):
    import socket

    web_port, grpc_port = free_port(), free_port()
    busy = socket.socket()
    busy.bind(("127.0.0.1", web_port if which == "web" else grpc_port))
    busy.listen()
    try:
        with pytest.raises(BttsimError) as err:
            open_recording(serve_web=True, web_port=web_port, grpc_port=grpc_port)
        assert "\n" not in str(err.value) and ("--web-port" if which == "web" else "--grpc-port") in str(err.value)
        other = grpc_port if which == "web" else web_port
        assert not can_connect("127.0.0.1", other)  # checked before anything started
    finally:
        busy.close()


def test_a_wildcard_listener_makes_the_loopback_port_busy():
    """Another program on 0.0.0.0:PORT also takes 127.0.0.1:PORT: the check says so."""
    import socket

    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(BttsimError, match="in use"):
            check_port_free("127.0.0.1", port, "web viewer (--web-port)")


@pytest.mark.parametrize("addr, expected", [("127.0.0.1", "127.0.0.1"), ("::1", "::1"), ("[::1]", "::1"),
                                            (" 0.0.0.0", "0.0.0.0")])
def test_parse_bind(addr, expected):
    assert parse_bind(addr) == expected


@pytest.mark.parametrize("addr", ["localhost", "127.0.0.256", "", "eth0"])
def test_parse_bind_refuses_what_is_not_an_ip_address(addr):
    with pytest.raises(BttsimError, match="not an IP address"):
        parse_bind(addr)


def test_url_host():
    assert [url_host(h) for h in ("127.0.0.1", "::1", "0.0.0.0", "::", "10.1.2.3")] == [
        "127.0.0.1", "[::1]", "127.0.0.1", "[::1]", "10.1.2.3"]


def test_same_web_and_grpc_port_is_an_error():
    port = free_port()
    with pytest.raises(BttsimError, match="both"):
        open_recording(serve_web=True, web_port=port, grpc_port=port)


@pytest.mark.integration
def test_view_web_serves_on_loopback_with_a_complete_rrd_and_stops_on_ctrl_c(tmp_path):
    """`bttsim view F.mcap --rrd OUT --web --web-port P --grpc-port G`: both servers on
    127.0.0.1 only, the .rrd already complete while serving, Ctrl-C ends it at once."""
    import signal
    import time

    from _procs import LineWatch

    web_port, grpc_port = free_port(), free_port()
    rrd = tmp_path / "v.rrd"
    proc = subprocess.Popen([sys.executable, "-m", "bttsim_stream.cli", "view",
                             str(REPO / "recordings" / "resonance_window.mcap"), "--rrd", str(rrd), "--web",
                             "--web-port", str(web_port), "--grpc-port", str(grpc_port)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = LineWatch(proc.stdout).wait_for(lambda ln: ln.startswith("web viewer:"), timeout=300)
        assert f"http://127.0.0.1:{web_port}/" in line
        mine = listening_of([proc.pid])
        assert ("127.0.0.1", web_port) in mine and ("127.0.0.1", grpc_port) in mine
        assert all(is_loopback(addr) for addr, _ in mine), mine
        res = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(rrd)], capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 0, res.stdout + res.stderr
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
        assert time.monotonic() - t0 < 10
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, proc.stderr.read()
    assert not can_connect("127.0.0.1", web_port)
