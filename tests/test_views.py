"""Rerun views: bulk logging of a recording, the live viewer node, and the web viewer (browser)."""

from __future__ import annotations

import collections
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from _procs import start as _start, stop as _stop
from bttsim_stream.bus import codec, keys
from bttsim_stream.bus.recording import McapRecorder, read_recording
from bttsim_stream.testing import free_port

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from bttsim_stream import views  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2500.0\nend_rpm = 2600.0\nduration_s = 3.0\n"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


# --------------------------------------------------------------------------------------
# Fixtures and helpers
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_mcap(tmp_path_factory) -> Path:
    """A 3 s recording from ``bttsim simulate`` (127 revolutions near resonance, with truth)."""
    tmp = tmp_path_factory.mktemp("views")
    scenario = tmp / "short.toml"
    scenario.write_text(SHORT)
    out = tmp / "short.mcap"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "simulate", str(scenario), "--out",
                          str(out), "-q"], cwd=REPO, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    return out


def add_processing(src: Path, dst: Path) -> dict:
    """Copy a recording and add hand-built processing messages derived from its truth.

    Per revolution, a least-squares EO sine fit of each blade's d_eqv over the probes
    (``d = Re(c exp(i EO phi)) + dc`` with ``phi`` the rotor angle at the crossing):
    ``BladeFits`` (``2 |c|``, ``arg c``) and one ``TravellingWave`` per probe (the spatial DFT
    of ``c`` over the blades: ND ``n`` forward ``|C_n|``, backward ``|C_-n|``); at the end one
    ``ResonanceReport`` (each blade's largest fitted amplitude against the truth envelope's).
    Returns message counts by kind.
    """
    recording = read_recording(src)
    meta = next(codec.decode_run_metadata(m.payload) for m in recording.messages if m.key.endswith("/meta"))
    rig, run_id, eo, nb = meta.rig, meta.run_id, meta.engine_orders[0], meta.n_blades
    phi = np.mod(meta.probe_angles_rad[None, :] - 2 * np.pi * np.arange(nb)[:, None] / nb - meta.opr_angle_rad,
                 2 * np.pi)
    basis = np.stack([np.cos(eo * phi), np.sin(eo * phi), np.ones_like(phi)], axis=-1)  # (nb, np, 3)
    pinv = np.linalg.pinv(basis)
    n_nd = nb // 2 + 1
    seqs: dict[str, int] = {}
    counts = collections.Counter()
    best = {"fit": np.zeros(nb), "fit_f": np.zeros(nb), "truth": np.zeros(nb), "truth_f": np.zeros(nb)}
    with McapRecorder(dst, run_metadata=recording.run_metadata) as out:
        for m in recording.messages:
            out.write(m.key, m.payload, m.log_time_ns, sequence=m.sequence)
            if not m.key.endswith("/truth"):
                continue
            tr = codec.decode_truth_batch(m.payload)
            rev, t = tr.header.revolution, tr.header.t_s
            coef = np.einsum("bkj,bj->bk", pinv, tr.d_eqv_m)
            c = coef[:, 0] - 1j * coef[:, 1]
            f = eo * tr.omega_mean_rad_s / (2 * np.pi)
            out.write(*codec.encode_blade_fits(
                run_id=run_id, rig=rig, seqs=seqs, revolution=rev, t_s=t, engine_order=eo,
                omega_mean_rad_s=tr.omega_mean_rad_s, cn=1.4, amp_pkpk_m=2 * np.abs(c), phase_rad=np.angle(c),
                dc_m=coef[:, 2], residual_m=np.full(nb, 1e-6), amp_std_m=np.full(nb, 1e-6)))
            counts["fit"] += 1
            spectrum = np.fft.fft(c) / nb
            for j in range(tr.n_probes):
                out.write(*codec.encode_travelling_wave(
                    run_id=run_id, rig=rig, seqs=seqs, revolution=rev, t_s=t, probe=j,
                    forward_m=np.abs(spectrum[:n_nd]), backward_m=np.abs(spectrum[(-np.arange(n_nd)) % nb])))
                counts["tw"] += 1
            for name, amp in (("fit", 2 * np.abs(c)), ("truth", tr.d_eqv_pkpk_m)):
                up = amp > best[name]
                best[name][up], best[name + "_f"][up] = amp[up], f
        blades = [{"blade": b, "amp_pkpk_m": best["fit"][b], "freq_hz": best["fit_f"][b],
                   "truth_amp_pkpk_m": best["truth"][b], "truth_freq_hz": best["truth_f"][b],
                   "E_A_pct": 100 * (best["fit"][b] / best["truth"][b] - 1),
                   "E_f_pct": 100 * (best["fit_f"][b] / best["truth_f"][b] - 1)} for b in range(nb)]
        e_a = np.abs([row["E_A_pct"] for row in blades])
        e_f = np.abs([row["E_f_pct"] for row in blades])
        report = {"nd": meta.nodal_diameters[0], "eo": eo, "cn": 1.4, "blades": blades,
                  "mean_E_A_pct": e_a.mean(), "max_E_A_pct": e_a.max(), "mean_E_f_pct": e_f.mean(),
                  "max_E_f_pct": e_f.max()}
        out.write(*codec.encode_resonance_report(report, run_id=run_id, rig=rig, seqs=seqs,
                                                 revolution=-1, t_s=recording.messages[-1].log_time_ns * 1e-9))
        counts["resonance"] += 1
    return dict(counts)


@pytest.fixture(scope="module")
def processed_mcap(short_mcap) -> Path:
    out = short_mcap.with_name("processed.mcap")
    add_processing(short_mcap, out)
    return out


def rrd_verify(path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def rrd_entities(path: Path) -> dict[str, dict]:
    """``entity path -> {"rows": temporal rows, "static": bool}`` of the recording store."""
    out: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        e = out.setdefault(chunk.entity_path, {"rows": 0, "static": False})
        if chunk.is_static:
            e["static"] = True
        else:
            e["rows"] += chunk.num_rows
    return out


# --------------------------------------------------------------------------------------
# Numerics
# --------------------------------------------------------------------------------------


def test_btt_displacement_matches_the_simulator_eq1_truth(short_mcap):
    recording = read_recording(short_mcap)
    msgs = [(m.key, codec.decode_message(m.key, m.payload)) for m in recording.messages]
    meta = msgs[0][1]
    opr = np.array([m.opr_s for k, m in msgs if k.endswith("/opr")])
    truth = [m for k, m in msgs if k.endswith("/truth")]
    toa = np.array([t.toa_s for t in truth])  # (n_rev, n_blades, n_probes), no acquisition errors
    d_eq1 = np.array([t.d_eq1_m for t in truth])
    from bttsim_stream.model import build_model
    from bttsim_stream.scenario import scenario_from_dict
    import tomllib

    model = build_model(scenario_from_dict(tomllib.loads(meta.scenario_toml)))
    blade_angles = model.tip_ref[:, model.nominal_node, 1]
    inner = slice(1, opr.size - 1)
    omega, accel = views.speed_from_opr(opr[:-2], opr[1:-1], opr[2:])
    d = views.btt_displacement(opr[inner], omega, accel, toa[inner], probe_angles_rad=meta.probe_angles_rad,
                               blade_angles_rad=blade_angles, opr_angle_rad=meta.opr_angle_rad,
                               tip_radius_m=meta.tip_radius_m)
    np.testing.assert_allclose(d, d_eq1[inner], rtol=0, atol=1e-9)
    # without the acceleration term the error is far larger (what the correction is for)
    d0 = views.btt_displacement(opr[inner], omega, np.zeros_like(accel), toa[inner],
                                probe_angles_rad=meta.probe_angles_rad, blade_angles_rad=blade_angles,
                                opr_angle_rad=meta.opr_angle_rad, tip_radius_m=meta.tip_radius_m)
    assert np.max(np.abs(d0 - d_eq1[inner])) > 1e-5


def test_speed_from_opr_of_a_constant_acceleration_is_exact():
    omega0, alpha = 260.0, 2.4  # rad/s, rad/s^2
    k = np.arange(8)
    t = (-omega0 + np.sqrt(omega0**2 + 2 * alpha * 2 * np.pi * k)) / alpha  # angle 2 pi k
    omega, accel = views.speed_from_opr(t[:-2], t[1:-1], t[2:])
    np.testing.assert_allclose(omega, 2 * np.pi / np.diff(t)[1:], rtol=1e-12)
    np.testing.assert_allclose(accel, alpha, rtol=1e-6)
    # the first revolution has no previous OPR: it takes its neighbour's acceleration
    _, accel_first = views.speed_from_opr([np.nan, t[0]], t[:2], t[1:3])
    np.testing.assert_allclose(accel_first, alpha, rtol=1e-6)


@pytest.mark.parametrize("n_probes", [1, 5], ids=["one-probe", "five-probes"])
def test_build_blueprint_has_a_travelling_wave_and_displacement_view_per_probe(n_probes):
    bp = views.build_blueprint(n_probes, n_blades=29)
    assert isinstance(bp, rr.blueprint.Blueprint)


# --------------------------------------------------------------------------------------
# Recordings
# --------------------------------------------------------------------------------------


def test_log_recording_of_a_raw_acquisition(short_mcap, tmp_path):
    out = tmp_path / "raw.rrd"
    session = views.log_recording(short_mcap, out)
    assert session.sinks.rrd_path == str(out) and session.stats["revolutions"] == 127
    assert session.stats["bad"] == 0 and session.stats["fits"] == 0
    rrd_verify(out)
    ent = rrd_entities(out)
    for probe in range(5):
        assert ent[f"/displacement/probe_{probe}/btt"]["rows"] == 127
        assert ent[f"/displacement/probe_{probe}/d_eqv"]["rows"] == 127
    for path in ("/speed/rpm", "/truth/amp_pkpk_mm", "/rotor/blades", "/campbell/speed"):
        assert ent[path]["rows"] == 127, path
    for path in ("/campbell/families", "/campbell/engine_orders", "/campbell/run_range", "/campbell/resonance",
                 "/rotor/casing", "/rotor/probes", "/rotor/opr"):
        assert ent[path]["static"], path
    assert not any(p.startswith(("/fit", "/tw", "/resonance")) for p in ent)  # no processing: empty views
    reader = RrdReader(out)
    assert [s.application_id for s in reader.blueprints()] == [views.APPLICATION_ID]


def test_log_recording_with_processing_messages(processed_mcap, tmp_path):
    out = tmp_path / "processed.rrd"
    session = views.log_recording(processed_mcap, out, blades=[3, 7, 11])
    assert session.stats["fits"] == 127 and session.stats["tw"] == 127 * 5 and session.stats["resonance"] == 1
    rrd_verify(out)
    ent = rrd_entities(out)
    for path in ("/fit/amp_pkpk_mm", "/fit/phase_deg", "/fit/freq_hz"):
        assert ent[path]["rows"] == 127, path
    for probe in range(5):
        assert ent[f"/tw/probe_{probe}"]["static"]
        assert ent[f"/tw/dominant_nd/probe_{probe}"]["rows"] == 127
    for path in ("/resonance/table", "/resonance/amp_pkpk_mm/btt", "/resonance/amp_pkpk_mm/d_eqv"):
        assert ent[path]["static"], path
    # the whole-run travelling wave: rows ND +14 (top) .. -14 (bottom), one column per revolution,
    # magnitudes in mm; each column's largest row is the message's dominant ND
    tensor = _static_tensor(out, "/tw/probe_0")
    assert tensor.shape == (29, 127)
    tws = [codec.decode_travelling_wave(m.payload) for m in read_recording(processed_mcap).messages
           if m.key == keys.tw_key("rig1", 0)]
    dominant = np.array([m.dominant_nd for m in tws])
    np.testing.assert_array_equal(14 - np.argmax(tensor, axis=0), dominant)
    np.testing.assert_allclose(tensor[14 - 3], [m.forward_m[3] * 1e3 for m in tws], rtol=1e-6)
    np.testing.assert_allclose(tensor[14 + 3], [m.backward_m[3] * 1e3 for m in tws], rtol=1e-6)
    assert "| 28 |" in _static_text(out, "/resonance/table")


def _static_column(path: Path, entity: str, suffix: str):
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and chunk.is_static:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name.endswith(suffix):
                    return batch.column(name)
    raise AssertionError(f"{entity}: no static {suffix}")


def _static_tensor(path: Path, entity: str) -> np.ndarray:
    col = _static_column(path, entity, ":data").to_pylist()[0][0]
    shape = col["shape"]
    buffer = col["buffer"]
    kind, values = buffer if isinstance(buffer, tuple) else (None, buffer)
    return np.asarray(values, dtype=np.float32).reshape(shape)


def _static_text(path: Path, entity: str) -> str:
    return _static_column(path, entity, ":text").to_pylist()[0][0]


def _temporal_scalars(path: Path, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """``(revolution (n,), values (n, k))`` of a Scalars entity, sorted by revolution."""
    revs, values = [], []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            revs += batch.column("revolution").to_pylist()
            values += batch.column("Scalars:scalars").to_pylist()
    order = np.argsort(revs)
    return np.asarray(revs)[order], np.asarray(values, float)[order]


def test_without_the_model_the_blade_angles_are_estimated(short_mcap, tmp_path):
    # the same run, but its scenario names a model file that does not exist here
    recording = read_recording(short_mcap)
    meta = codec.decode_run_metadata(recording.messages[0].payload)
    toml = meta.scenario_toml.replace('source = "builtin"', 'source = "/nonexistent/model.npz"')
    assert toml != meta.scenario_toml
    moved = tmp_path / "no-model.mcap"
    with McapRecorder(moved, run_metadata=recording.run_metadata) as out:
        out.write(recording.messages[0].key, codec.encode_run_metadata(meta.to_run_info(), meta.run_id, toml,
                                                                       meta.software_version, True), 0)
        for m in recording.messages[1:]:
            out.write(m.key, m.payload, m.log_time_ns, sequence=m.sequence)
    out_rrd = tmp_path / "no-model.rrd"
    views.log_recording(moved, out_rrd)
    rrd_verify(out_rrd)
    ent = rrd_entities(out_rrd)
    assert "/campbell/families" not in ent and ent["/campbell/engine_orders"]["static"]
    revs, d_mm = _temporal_scalars(out_rrd, "/displacement/probe_2/btt")  # blades 0 and 14
    truth = np.array([codec.decode_truth_batch(m.payload).d_eq1_m[[0, 14], 2] for m in recording.messages
                      if m.key.endswith("/truth")])
    inner = slice(1, -1)  # the first and last revolutions lack a neighbouring OPR
    np.testing.assert_allclose(d_mm[inner] * 1e-3, truth[revs][inner], rtol=0, atol=1e-6)


def test_log_recording_bad_input_is_a_one_line_error(tmp_path):
    from bttsim_stream.errors import BttsimError

    with pytest.raises(BttsimError):
        views.log_recording(tmp_path / "missing.mcap", tmp_path / "x.rrd")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(BttsimError):
        views.log_recording(bad, tmp_path / "x.rrd")


def test_live_views_fed_message_by_message_match_the_bulk_log(processed_mcap, tmp_path):
    out = tmp_path / "live.rrd"
    rec, sinks = views.open_recording(rrd_path=out)
    live = views.LiveViews(rec, live=True, flush_period_s=0.01, tw_window=32, tw_period_s=0.0)
    for m in read_recording(processed_mcap).messages:
        live.feed(m.key, m.payload)
    live.feed("bttsim/rig1/alive/sim", b"")           # not a message: ignored
    live.feed("bttsim/rig1/opr", b"\xff\xff garbage")  # counted, skipped
    live.close()
    rec.disconnect()
    assert live.stats["revolutions"] == 127 and live.stats["bad"] == 1 and live.stats["ignored"] == 1
    rrd_verify(out)
    ent = rrd_entities(out)
    assert ent["/speed/rpm"]["rows"] == 127 and ent["/displacement/probe_4/btt"]["rows"] == 127
    assert ent["/tw/probe_0"]["rows"] > 1 and not ent["/tw/probe_0"]["static"]  # a rolling window
    assert ent["/resonance/table"]["rows"] == 1


# --------------------------------------------------------------------------------------
# The viewer node (real processes on loopback)
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("stop_by", ["sim-ends", "sigterm"])
def test_viewer_node_follows_a_live_simulator_and_leaves_a_valid_rrd(short_mcap, tmp_path, stop_by):
    scenario = tmp_path / "short.toml"
    scenario.write_text(SHORT)
    port = free_port()
    out = tmp_path / "live.rrd"
    viewer = _start("bttsim_stream.nodes.viewer_node", "-e", f"tcp/127.0.0.1:{port}", "--rig", "rig1",
                    "--rrd", out)
    rate = "10" if stop_by == "sim-ends" else "0.3"  # 0.3: a 10 s run, stopped after ~4 s
    sim = _start("bttsim_stream.nodes.sim_node", scenario, "-l", f"tcp/127.0.0.1:{port}", "--rate", rate,
                 "--wait-for", "1")
    try:
        if stop_by == "sim-ends":
            assert sim.wait(timeout=120) == 0, sim.stderr.read()
            _, err = viewer.communicate(timeout=60)  # the viewer stops when the simulator is gone
        else:
            time.sleep(4.0)
            assert viewer.poll() is None and sim.poll() is None
            viewer.send_signal(signal.SIGTERM)
            _, err = viewer.communicate(timeout=60)
        assert viewer.returncode == 0, err
    finally:
        _stop(sim), _stop(viewer)
    rrd_verify(out)
    ent = rrd_entities(out)
    rows = ent["/speed/rpm"]["rows"]
    if stop_by == "sim-ends":
        assert rows == 127
        assert ent["/displacement/probe_0/btt"]["rows"] == 127 and ent["/truth/amp_pkpk_mm"]["rows"] == 127
    else:
        assert 0 < rows < 127
    assert ent["/campbell/families"]["static"] and ent["/rotor/blades"]["rows"] == rows


def test_viewer_node_without_an_output_is_a_one_line_error():
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.nodes.viewer_node", "--rig", "rig1"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip().startswith("bttsim: error:") and len(res.stderr.strip().splitlines()) == 1


# --------------------------------------------------------------------------------------
# The web viewer in headless Chromium (slow: software rendering)
# --------------------------------------------------------------------------------------

_SERVE = textwrap.dedent("""
    import sys, time
    from bttsim_stream import views
    s = views.log_recording(sys.argv[1], None, serve_web=True, web_port=int(sys.argv[2]),
                            grpc_port=int(sys.argv[3]))
    print(s.sinks.web_url, flush=True)
    time.sleep(float(sys.argv[4]))
""")

_CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _loopback_only(route):
    from urllib.parse import urlparse

    host = urlparse(route.request.url).hostname
    if host in ("127.0.0.1", "localhost") or route.request.url.startswith(("data:", "blob:")):
        return route.continue_()
    return route.abort()


def _capture(url: str | None, path: Path, user_data: Path, *, budget_s: float, first_wait_s: float = 45.0,
             every_s: float = 15.0, done=lambda pixels: True) -> np.ndarray:
    """Open ``url`` (or a blank page) in headless Chromium and screenshot it to ``path`` every
    ``every_s`` after ``first_wait_s`` until ``done(pixels)`` or ``budget_s`` is spent; returns
    the last screenshot's RGB pixels. Only loopback requests are let through."""
    from playwright.sync_api import sync_playwright

    deadline = time.monotonic() + budget_s
    with sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(str(user_data), executable_path=CHROMIUM,
                                                   args=_CHROMIUM_ARGS, headless=True,
                                                   viewport={"width": 1600, "height": 1000})
        try:
            page = ctx.new_page()
            page.route("**/*", _loopback_only)
            if url:
                page.goto(url, wait_until="domcontentloaded", timeout=120_000)
            page.wait_for_timeout(first_wait_s * 1000)
            while True:
                page.screenshot(path=str(path), timeout=180_000)
                pixels = _png_rgb(path)
                if done(pixels) or time.monotonic() > deadline:
                    return pixels
                page.wait_for_timeout(every_s * 1000)
        finally:
            ctx.close()


def _png_rgb(path: Path) -> np.ndarray:
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    if img.dtype != np.uint8:
        img = np.round(img * 255).astype(np.uint8)
    return img[..., :3]


def _n_colours(pixels: np.ndarray) -> int:
    flat = pixels.reshape(-1, 3).astype(np.int64)
    return np.unique((flat[:, 0] << 16) | (flat[:, 1] << 8) | flat[:, 2]).size


def _plot_checks(pixels: np.ndarray) -> dict[str, bool]:
    """What the overview tab must show once drawn (1600 x 1000 page, 3 x 2 grid of views)."""
    h, w = pixels.shape[:2]
    background = np.median(pixels.reshape(-1, 3), axis=0)
    busy = np.abs(pixels.astype(int) - background).sum(axis=2) > 60
    cells = [busy[r * h // 2:(r + 1) * h // 2, c * w // 3:(c + 1) * w // 3].mean()
             for r in range(2) for c in range(3)]
    top_left, top_right = pixels[90:h // 2, :w // 3], pixels[90:h // 2, 2 * w // 3:]
    return {
        # many colours (heat map, blade colours, lines), spread over the page
        "many colours": _n_colours(pixels) > 800,
        "5 of 6 views drawn": sum(c > 0.01 for c in cells) >= 5,
        # ours specifically: the travelling-wave heat map (a colour gradient, top left) and
        # blade 0 in orange in the rotor view (top right)
        "heat map": _n_colours(top_left) > 100,
        "rotor": int((np.abs(top_right.astype(int) - [230, 120, 20]).sum(axis=2) < 60).sum()) > 50,
    }


@pytest.mark.browser
def test_web_viewer_draws_the_plots(processed_mcap, tmp_path):
    if CHROMIUM is None:
        pytest.skip("Chromium not installed (apt-get install chromium)")
    pytest.importorskip("playwright", reason="Playwright not installed (pip install playwright)")
    if os.environ.get("BTTSIM_NETNS") != "1":
        # Rerun's web page server binds every interface (no bind option in 0.41): run the
        # server and the browser in a private network namespace that has only loopback
        if shutil.which("unshare") is None or subprocess.run(
                ["unshare", "-n", "true"], capture_output=True).returncode != 0:
            pytest.skip("needs 'unshare -n' (a loopback-only network namespace) for the web viewer")
        test_id = f"{Path(__file__).resolve()}::test_web_viewer_draws_the_plots"
        res = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up && exec \"$@\"", "sh",
                              "env", "BTTSIM_NETNS=1", sys.executable, "-m", "pytest", "-q", "-p",
                              "no:cacheprovider", test_id], cwd=REPO, capture_output=True, text=True,
                             timeout=900)
        assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
        return
    web_port, grpc_port = free_port(), free_port()
    log_path = tmp_path / "server.log"
    with open(log_path, "w") as log_file:  # a file, not a pipe: the server logs for minutes
        server = subprocess.Popen([sys.executable, "-c", _SERVE, str(processed_mcap), str(web_port),
                                   str(grpc_port), "600"], cwd=REPO, stdout=subprocess.PIPE, stderr=log_file,
                                  text=True)
    try:
        url = server.stdout.readline().strip()
        assert url.startswith(f"http://127.0.0.1:{web_port}/"), log_path.read_text()[-2000:]
        blank = _capture(None, tmp_path / "blank.png", tmp_path / "profile-blank", budget_s=0, first_wait_s=1)
        shot = tmp_path / "views.png"
        pixels = _capture(url, shot, tmp_path / "profile", budget_s=420,
                          done=lambda px: all(_plot_checks(px).values()))
    finally:
        _stop(server)
    assert not any(_plot_checks(blank).values())
    checks = _plot_checks(pixels)
    assert all(checks.values()), f"{checks}: see {shot}"
    target = os.environ.get("BTTSIM_SAVE_SCREENSHOT")
    if target:
        shutil.copyfile(shot, target)


def test_bttsim_view_of_the_sample_recording(tmp_path):
    """`bttsim view recordings/<sample>.mcap --rrd out.rrd`: processed first, every view present."""
    out = tmp_path / "sample.rrd"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "view",
                          str(REPO / "recordings" / "resonance_window.mcap"), "--rrd", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    rrd_verify(out)
    ent = rrd_entities(out)
    for path in ("/tw/probe_0", "/fit/amp_pkpk_mm", "/truth/amp_pkpk_mm", "/displacement/probe_0/btt",
                 "/rotor/blades", "/campbell/families", "/resonance/table"):
        assert path in ent, path
