"""Rerun views of a BTT run: travelling waves, blade fits, raw BTT displacement, rotor, Campbell.

This is the only library module that imports :mod:`rerun`. It turns decoded bus messages
(:mod:`bttsim_stream.io.codec`) into Rerun entities, in bulk (``send_columns``), either for a
whole recording at once (:func:`log_recording`) or message by message from a live bus
(:class:`LiveViews`, flushed every ``flush_period_s``). The default layout is built in one
place, :func:`build_blueprint`. Entity paths and what each view shows are listed in
``docs/views.md``.

Conventions:

* Timelines: ``revolution`` (sequence, the header revolution index) and ``time`` (duration,
  the simulated time of the message in s: the OPR time for per-revolution data).
* Display units: mm for displacements and amplitudes, degrees for phases, rpm and Hz for
  speeds and frequencies (the entity path or series name says which).
* 2-D views (rotor, Campbell) put +x to the right and +y up: Rerun's 2-D space has y down, so
  positions are logged as ``(x, -y)``. Angles are anticlockwise from +x, as in the model.
* A recording is complete, so its travelling-wave matrices, Campbell diagram and resonance
  table are static; live, the travelling wave is a rolling window re-logged on the
  ``revolution`` timeline at most every ``tw_period_s``, and the resonance table is logged
  at each report.

Recordings without ``BladeFits`` / ``TravellingWave`` / ``ResonanceReport`` messages (a raw
acquisition) leave those views empty: this module does not fit; ``bttsim view`` runs the
processor first.
"""

from __future__ import annotations

import logging
import math
import socket
import time
import tomllib
import urllib.parse
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from .errors import BttsimError
from .io import codec, keys

__all__ = [
    "APPLICATION_ID",
    "DEFAULT_EXAGGERATION",
    "ViewSinks",
    "ViewSession",
    "LiveViews",
    "build_blueprint",
    "btt_displacement",
    "speed_from_opr",
    "open_recording",
    "log_recording",
    "tw_path",
    "displacement_path",
]

log = logging.getLogger("bttsim.views")

#: Rerun application id of every bttsim recording (blueprints are stored per application).
APPLICATION_ID = "bttsim"
#: Default exaggeration of the tip deflection in the rotor view.
DEFAULT_EXAGGERATION = 20.0
TWO_PI = 2.0 * math.pi
_MM = 1e3
_MAX_EO = 12
_HUB_RATIO = 0.55
_CASING_RATIO = 1.1
_GREY = (150, 150, 150)
_CAMPBELL_HEIGHT = 1.0 / 1.6  # height of the Campbell plot box (its width is 1)
_FAMILY_COLORS = ((31, 119, 180), (148, 103, 189), (23, 190, 207), (140, 86, 75), (127, 127, 127))


def tw_path(probe: int) -> str:
    """Entity of the travelling-wave matrix of one probe: ``tw/probe_<j>``."""
    return f"tw/probe_{int(probe)}"


def displacement_path(probe: int) -> str:
    """Parent entity of one probe's raw BTT displacement: ``displacement/probe_<j>``."""
    return f"displacement/probe_{int(probe)}"


# --------------------------------------------------------------------------------------
# Numerics (numpy only)
# --------------------------------------------------------------------------------------


def speed_from_opr(t_prev_s, t_opr_s, t_next_s) -> tuple[np.ndarray, np.ndarray]:
    """Mean speed and angular acceleration of each revolution from three consecutive OPRs.

    Parameters
    ----------
    t_prev_s, t_opr_s, t_next_s : array_like, shape (n_rev,)
        OPR times of revolutions ``k - 1``, ``k`` and ``k + 1``, s. NaN where unknown.

    Returns
    -------
    omega_mean_rad_s : ndarray, shape (n_rev,)
        ``2 pi / (t_next - t_opr)``, rad/s.
    accel_rad_s2 : ndarray, shape (n_rev,)
        ``(Omega_k - Omega_{k-1}) / ((T_k + T_{k-1}) / 2)``, rad/s^2; where ``t_prev`` is
        unknown, the nearest known value (0 if none).
    """
    t_prev = np.asarray(t_prev_s, float)
    t0 = np.asarray(t_opr_s, float)
    t1 = np.asarray(t_next_s, float)
    period = t1 - t0
    period_prev = t0 - t_prev
    omega = TWO_PI / period
    with np.errstate(invalid="ignore", divide="ignore"):
        accel = (omega - TWO_PI / period_prev) / (0.5 * (period + period_prev))
    ok = np.isfinite(accel)
    if not ok.all():
        if ok.any():
            idx = np.flatnonzero(ok)
            near = idx[np.clip(np.searchsorted(idx, np.arange(accel.size)), 0, idx.size - 1)]
            accel = np.where(ok, accel, accel[near])
        else:
            accel = np.zeros_like(accel)
    return omega, accel


def btt_displacement(t_opr_s, omega_mean_rad_s, accel_rad_s2, toa_s, *, probe_angles_rad,
                     blade_angles_rad, opr_angle_rad: float, tip_radius_m: float) -> np.ndarray:
    """Raw BTT tip displacement (Eq. 1) from OPR and TOAs with the nominal geometry.

    Parameters
    ----------
    t_opr_s, omega_mean_rad_s, accel_rad_s2 : array_like, shape (n_rev,)
        OPR time (s), mean speed over the revolution (rad/s) and angular acceleration
        (rad/s^2), e.g. from :func:`speed_from_opr`.
    toa_s : array_like, shape (n_rev, n_blades, n_probes)
        Times of arrival, s (NaN where missing).
    probe_angles_rad : array_like, shape (n_probes,)
    blade_angles_rad : array_like, shape (n_blades,)
        Angle of each blade's nominal sensing point P_nom in the rotor frame at t = 0, rad.
    opr_angle_rad, tip_radius_m : float

    Returns
    -------
    ndarray, shape (n_rev, n_blades, n_probes)
        ``d = Omega R (t_exp - t_TOA)``, m; positive when the tip leads (rotation direction).

    Notes
    -----
    Eq. 1 of the paper with ``Omega`` the revolution's mean speed and ``R`` the tip radius.
    The expected time ``t_exp`` is when P_nom would reach the probe if the blade did not
    vibrate: the rotor turns ``psi = (theta_probe - theta_blade - theta_opr) mod 2 pi`` after
    the OPR, at a speed that changes linearly within the revolution (``omega_0 + alpha tau``
    with ``omega_0 = Omega - alpha T / 2`` so that one revolution takes ``T = 2 pi / Omega``):
    ``tau = 2 psi / (omega_0 + sqrt(omega_0^2 + 2 alpha psi))``. Without the acceleration
    term (``t_exp = t_opr + psi / Omega``) a 23 rpm/s run-up gives errors up to about 0.2 mm
    near 2500 rpm; with it, the default run matches the simulator's exact ``d_eq1`` to
    1e-11 m.
    """
    toa = np.asarray(toa_s, float)
    t0 = np.asarray(t_opr_s, float)[:, None, None]
    omega = np.asarray(omega_mean_rad_s, float)[:, None, None]
    alpha = np.asarray(accel_rad_s2, float)[:, None, None]
    psi = np.mod(np.asarray(probe_angles_rad, float)[None, :]
                 - np.asarray(blade_angles_rad, float)[:, None] - opr_angle_rad, TWO_PI)[None]
    w0 = omega - alpha * (TWO_PI / omega) / 2.0
    tau = 2.0 * psi / (w0 + np.sqrt(np.maximum(w0 * w0 + 2.0 * alpha * psi, 0.0)))
    return omega * tip_radius_m * (t0 + tau - toa)


def _signed_spectrum(forward_m: np.ndarray, backward_m: np.ndarray) -> np.ndarray:
    """Rows ND = +(n-1) .. 0 .. -(n-1) (forward positive), shape (2 n - 1,)."""
    zero = np.fmax(forward_m[:1], backward_m[:1])
    return np.concatenate([forward_m[:0:-1], zero, backward_m[1:]])


def _palette(n: int) -> np.ndarray:
    """``n`` distinct colours around the hue circle, uint8 (n, 3)."""
    h = np.arange(n) / max(n, 1)
    k = np.mod(np.array([5.0, 3.0, 1.0])[None, :] + 6.0 * h[:, None], 6.0)
    rgb = 0.85 - 0.6 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)  # HSV, s = 0.7, v = 0.85
    return np.round(255 * rgb).astype(np.uint8)


_SELECTION = np.array([(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14),
                       (140, 86, 75)], np.uint8)


def _selection_colors(n: int, light: bool = False) -> np.ndarray:
    """Colours of the selected blades (uint8 (n, 3)); ``light``: blended halfway to white."""
    c = _SELECTION[np.arange(n) % len(_SELECTION)].astype(float)
    return np.round(c + 0.5 * (255.0 - c) if light else c).astype(np.uint8)


def _screen(r, a) -> np.ndarray:
    """Polar (radius, angle anticlockwise) to Rerun 2-D coordinates (y down), last axis 2."""
    r, a = np.broadcast_arrays(np.asarray(r, float), np.asarray(a, float))
    return np.stack([r * np.cos(a), -r * np.sin(a)], axis=-1)


def _nice_ceil(x: float) -> float:
    step = 10.0 ** math.floor(math.log10(max(x, 1e-9)))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * step >= x:
            return m * step
    return 10.0 * step


# --------------------------------------------------------------------------------------
# Blueprint
# --------------------------------------------------------------------------------------


def _tw_view(probe: int, n_nd: int | None, live: bool) -> rrb.TensorView:
    rows = f"ND +{n_nd - 1} top to -{n_nd - 1} bottom" if n_nd else "ND + top to - bottom"
    span = "rolling window" if live else "whole run"
    return rrb.TensorView(
        origin=tw_path(probe), name=f"Travelling wave, probe {probe} ({rows}; {span})",
        slice_selection=rrb.TensorSliceSelection(width=1, height=0),
        scalar_mapping=rrb.TensorScalarMapping(colormap="turbo", mag_filter="nearest", gamma=0.5),
        view_fit="Fill")


def _amplitude_view() -> rrb.TimeSeriesView:
    return _series_view(origin="/", contents=["+ /fit/amp_pkpk_mm", "+ /truth/amp_pkpk_mm"],
                        name="Amplitude pk-pk (mm): fit (colour) and d_eqv truth (grey)",
                        plot_legend=rrb.PlotLegend(visible=False))


def _displacement_view(probe: int) -> rrb.TimeSeriesView:
    return _series_view(origin=displacement_path(probe),
                        name=f"Raw BTT displacement (mm), probe {probe}: Eq. 1 (points), d_eqv (line)")


def _rotor_view() -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin="rotor", name="Rotor at each OPR (tip deflection x exaggeration)",
                             visual_bounds=rrb.VisualBounds2D(x_range=[-1.5, 1.5], y_range=[-1.5, 1.5]))


def _campbell_view() -> rrb.Spatial2DView:
    return rrb.Spatial2DView(origin="campbell", name="Campbell diagram (x: rpm, y: Hz)",
                             visual_bounds=rrb.VisualBounds2D(x_range=[-0.14, 1.3],
                                                              y_range=[-1.1 * _CAMPBELL_HEIGHT, 0.08]))


def _series_view(**kwargs) -> rrb.TimeSeriesView:
    """A time-series view showing the whole run (not a window around the time cursor)."""
    whole = rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    return rrb.TimeSeriesView(axis_x=rrb.TimeAxis(view_range=whole), **kwargs)


def _table_view() -> rrb.TextDocumentView:
    return rrb.TextDocumentView(origin="resonance/table", name="Resonance per blade")


def build_blueprint(n_probes: int, *, n_blades: int | None = None, live: bool = False,
                    active_tab: int = 0) -> rrb.Blueprint:
    """The default layout of the bttsim views.

    Tabs: *Overview* (travelling wave of probe 0, amplitudes, rotor, displacement at probe
    0, Campbell diagram, resonance table), *Fits* (amplitude, phase, speed, frequency),
    *Travelling wave* (every probe and the dominant nodal diameter), *Displacement* (every
    probe), *Rotor & Campbell*, *Resonance* (table and per-blade amplitude bars).

    Parameters
    ----------
    n_probes : int
    n_blades : int, optional
        Names the nodal-diameter rows of the travelling-wave views.
    live : bool
        Names the travelling-wave views as rolling windows.
    active_tab : int
    """
    n_probes = int(n_probes)
    n_nd = n_blades // 2 + 1 if n_blades else None
    overview = rrb.Grid(
        _tw_view(0, n_nd, live), _amplitude_view(), _rotor_view(),
        _displacement_view(0), _campbell_view(), _table_view(),
        grid_columns=3, name="Overview")
    fits = rrb.Vertical(
        _amplitude_view(),
        _series_view(origin="fit/phase_deg", name="Fitted phase (deg)",
                     plot_legend=rrb.PlotLegend(visible=False)),
        rrb.Horizontal(
            _series_view(origin="speed/rpm", name="Speed (rpm, from the OPR)"),
            _series_view(origin="/", contents=["+ /fit/freq_hz", "+ /speed/eo_freq_hz"],
                         name="Frequency (Hz): fit f_BTT and EO x speed")),
        row_shares=[3, 2, 2], name="Fits")
    tw = rrb.Grid(*[_tw_view(j, n_nd, live) for j in range(n_probes)],
                  _series_view(origin="tw/dominant_nd", name="Dominant ND (backward < 0)"),
                  name="Travelling wave")
    disp = rrb.Grid(*[_displacement_view(j) for j in range(n_probes)], name="Displacement")
    rotor = rrb.Horizontal(_rotor_view(), _campbell_view(), name="Rotor & Campbell")
    resonance = rrb.Horizontal(
        _table_view(),
        rrb.BarChartView(origin="resonance/amp_pkpk_mm",
                         name="Resonant amplitude pk-pk (mm) per blade: BTT (left), d_eqv (right)"),
        name="Resonance")
    return rrb.Blueprint(
        rrb.Tabs(overview, fits, tw, disp, rotor, resonance, active_tab=active_tab),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline="revolution"))


# --------------------------------------------------------------------------------------
# Sinks
# --------------------------------------------------------------------------------------


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
                   web_port: int = 9090, grpc_port: int = 9876, blueprint: rrb.Blueprint | None = None,
                   recording_id: str | None = None, server_memory_limit: str = "512MiB",
                   ) -> tuple[rr.RecordingStream, ViewSinks]:
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
    blueprint : Blueprint, optional
        Default blueprint (else send one later with ``send_blueprint``).
    recording_id : str, optional
        E.g. the run id, so that re-logging the same run replaces it in a viewer.

    Raises
    ------
    BttsimError
        If no sink is requested.
    """
    if not (rrd_path or grpc_url or serve_web):
        raise BttsimError("no Rerun output: give an .rrd file, a viewer URL or the web viewer")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    sinks: list = []
    server_url = web_url = None
    if rrd_path:
        Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(rrd_path)))
    if grpc_url:
        sinks.append(rr.GrpcSink(grpc_url))
    if serve_web:
        for port, what in ((grpc_port, "gRPC"), (web_port, "web viewer")):
            _check_port_free(int(port), what)
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


# --------------------------------------------------------------------------------------
# Run geometry and model
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class _Geometry:
    blade_angles_rad: np.ndarray  # (n_blades,) P_nom angle at t = 0
    source: str                   # "model" or "estimated"


def _model_from_meta(meta: codec.RunMetadataMsg):
    """The run's modal model from the scenario in the metadata, or None (logged)."""
    from .model import build_model, load_model
    from .scenario import scenario_from_dict

    try:
        scn = scenario_from_dict(tomllib.loads(meta.scenario_toml), "run metadata scenario")
        model = build_model(scn) if scn.model.source == "builtin" else load_model(scn.model.source)
    except (BttsimError, OSError, ValueError, tomllib.TOMLDecodeError) as exc:
        log.warning("no modal model for the views (%s): Campbell lines left out, blade angles "
                    "estimated from the first revolutions", " ".join(str(exc).split()))
        return None
    if model.n_blades != meta.n_blades:
        log.warning("the scenario's model has %d blades, the run %d: model not used",
                    model.n_blades, meta.n_blades)
        return None
    return model


def _estimate_blade_angles(meta, t_opr, omega, accel, toa) -> np.ndarray:
    """``2 pi b / N_b`` plus a common P_nom offset: the circular mean over the revolutions,
    blades and probes given of the angle that puts each blade at its probe at its TOA."""
    nb = meta.n_blades
    tau = toa - t_opr[:, None, None]
    w0 = omega - accel * (TWO_PI / omega) / 2.0
    turned = w0[:, None, None] * tau + 0.5 * accel[:, None, None] * tau * tau
    theta = meta.probe_angles_rad[None, None, :] - meta.opr_angle_rad - turned
    offset = theta - (TWO_PI * np.arange(nb) / nb)[None, :, None]
    z = np.exp(1j * offset[np.isfinite(offset)])
    mean = float(np.angle(z.mean())) if z.size else 0.0
    return TWO_PI * np.arange(nb) / nb + mean


# --------------------------------------------------------------------------------------
# Live / bulk views
# --------------------------------------------------------------------------------------


class LiveViews:
    """Turn bus messages into Rerun views, batching them into ``send_columns`` calls.

    Feed messages with :meth:`feed` (raw payloads) in bus order; the views are flushed
    every ``flush_period_s`` (checked on each :meth:`feed` and :meth:`poll`) and on
    :meth:`close`.

    Parameters
    ----------
    recording : rerun.RecordingStream
        With its sinks already set (:func:`open_recording`).
    live : bool
        True: travelling waves as a rolling window of ``tw_window`` revolutions re-logged
        at most every ``tw_period_s``; resonance tables logged as they come. False (a whole
        recording, flushed once on close): whole-run travelling-wave matrices and the last
        resonance report, static.
    blades : sequence of int, optional
        Blades whose raw displacement is shown; default blade 0 and blade ``n_blades // 2``.
    exaggeration : float
        Tip deflection gain of the rotor view.
    flush_period_s, tw_window, tw_period_s : float, int, float
    send_blueprint : bool
        Send :func:`build_blueprint` when the run metadata arrives (not needed when the
        sinks were opened with it as the default).

    Notes
    -----
    A revolution's speed, raw displacement and rotor frame are logged once the next
    revolution's OPR has arrived (its mean speed needs it), so they lag one revolution;
    :meth:`close` extrapolates the last one. The displacement needs the run metadata (probe
    and OPR angles, tip radius) and the blade angles: from the scenario's modal model when
    it can be built, else estimated from the first revolutions.
    """

    def __init__(self, recording: rr.RecordingStream, *, live: bool = True,
                 blades: Sequence[int] | None = None, exaggeration: float = DEFAULT_EXAGGERATION,
                 flush_period_s: float = 0.2, tw_window: int = 256, tw_period_s: float = 1.0,
                 send_blueprint: bool = True) -> None:
        self.rec = recording
        self.live = bool(live)
        self.exaggeration = float(exaggeration)
        self.flush_period_s = float(flush_period_s)
        self.tw_window = int(tw_window)
        self.tw_period_s = float(tw_period_s)
        self._blades_req = None if blades is None else tuple(int(b) for b in blades)
        self._send_blueprint = send_blueprint
        self.meta: codec.RunMetadataMsg | None = None
        self._geom: _Geometry | None = None
        self._campbell: np.ndarray | None = None
        self._cb_scale: tuple[float, float] | None = None  # Campbell axes tops: (rpm, Hz)
        self._opr: dict[int, float] = {}
        self._pending: set[int] = set()       # revolutions with an OPR, not yet logged
        self._toa: dict[int, np.ndarray] = {}  # revolution -> (n_blades, n_probes)
        self._toa_seen: dict[int, int] = {}
        self._truth: list[codec.TruthBatchMsg] = []
        self._fits: list[codec.BladeFitsMsg] = []
        self._tw_new: list[codec.TravellingWaveMsg] = []
        self._tw: dict[int, dict[int, np.ndarray]] = {}  # probe -> revolution -> signed spectrum
        self._tw_max = 0.0
        self._tw_last_log = -math.inf
        self._resonance: codec.ResonanceReportMsg | None = None
        self._early: list = []
        self._styled: set[str] = set()
        self._next_seq: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self._closed = False
        self.stats = {"messages": 0, "ignored": 0, "bad": 0, "revolutions": 0, "fits": 0,
                      "tw": 0, "truth": 0, "resonance": 0}

    # -- input ---------------------------------------------------------------------------
    def feed(self, key: str, payload: bytes) -> None:
        """Decode and buffer one message (payloads that do not decode are counted, skipped)."""
        try:
            info = keys.parse_key(key)
        except BttsimError:
            self.stats["ignored"] += 1
            return
        if info.message_type is None or (self.meta is not None and info.rig != self.meta.rig):
            self.stats["ignored"] += 1
            return
        try:
            msg = codec.decode_message(key, payload)
        except BttsimError as exc:
            self.stats["bad"] += 1
            if self.stats["bad"] <= 3:
                log.warning("skipped a message: %s", exc)
            return
        seq = msg.header.seq
        if seq < self._next_seq.get(key, 0):  # a history sample already received live
            self.stats["ignored"] += 1
            return
        self._next_seq[key] = seq + 1
        self.feed_message(info.kind, msg)

    def feed_message(self, kind: str, msg) -> None:
        """Buffer one decoded message; ``kind`` is the key kind (``"opr"``, ``"toa"``, ...)."""
        self.stats["messages"] += 1
        self._dispatch(kind, msg)
        self.poll()

    def _dispatch(self, kind: str, msg) -> None:
        if kind == "meta":
            self._on_meta(msg)
        elif self.meta is None and kind in ("opr", "toa"):
            self._early.append((kind, msg))
        elif kind == "opr":
            rev = msg.header.revolution
            self._opr[rev] = msg.opr_s
            self._pending.add(rev)
        elif kind == "toa":
            self._on_toa(msg)
        elif kind == "truth":
            self._truth.append(msg)
        elif kind == "fit":
            self._fits.append(msg)
        elif kind == "tw":
            self._tw_new.append(msg)
        elif kind == "resonance":
            self._resonance = msg
            self.stats["resonance"] += 1

    def _on_meta(self, meta: codec.RunMetadataMsg) -> None:
        if self.meta is not None:
            if meta.run_id != self.meta.run_id:
                log.warning("ignoring run %s: already showing run %s", meta.run_id, self.meta.run_id)
            return
        self.meta = meta
        if self._send_blueprint:
            self.rec.send_blueprint(build_blueprint(meta.n_probes, n_blades=meta.n_blades, live=self.live))
        self._log_static_run()
        early, self._early = self._early, []
        for kind, msg in early:
            self._dispatch(kind, msg)

    def _on_toa(self, msg: codec.ToaBatchMsg) -> None:
        rev, nb, npr = msg.header.revolution, self.meta.n_blades, self.meta.n_probes
        if not 0 <= msg.probe < npr or msg.toa_s.size != nb:
            self.stats["bad"] += 1
            return
        row = self._toa.get(rev)
        if row is None:
            row = self._toa[rev] = np.full((nb, npr), np.nan)
        row[:, msg.probe] = msg.toa_s
        self._toa_seen[rev] = self._toa_seen.get(rev, 0) + 1

    # -- output --------------------------------------------------------------------------
    def poll(self) -> bool:
        """Flush if ``flush_period_s`` has passed since the last flush (live only)."""
        if self.live and time.monotonic() - self._last_flush >= self.flush_period_s:
            self.flush()
            return True
        return False

    def flush(self, *, final: bool = False) -> None:
        """Send everything buffered that can be shown now (``final``: all of it)."""
        self._last_flush = time.monotonic()
        if self.meta is not None:
            self._flush_revolutions(final)
        self._flush_truth()
        self._flush_fits()
        self._flush_tw(final)
        if self._resonance is not None and (self.live or final):
            self._log_resonance(self._resonance)
            self._resonance = None

    def close(self) -> None:
        """Flush everything (the last revolution's speed is extrapolated) and the stream."""
        if self._closed:
            return
        self._closed = True
        if self.meta is None and self._early:
            log.warning("no run metadata received: OPR/TOA views (speed, displacement, rotor) left empty")
        self.flush(final=True)
        self.rec.flush()

    # -- helpers -------------------------------------------------------------------------
    def _blades(self, nb: int) -> tuple[int, ...]:
        req = self._blades_req if self._blades_req is not None else (0, nb // 2)
        return tuple(dict.fromkeys(b for b in req if 0 <= b < nb))

    def _style(self, path: str, style) -> None:
        if path not in self._styled:
            self._styled.add(path)
            self.rec.log(path, style, static=True)

    def _scalars(self, path: str, revs: np.ndarray, t_s: np.ndarray, values: np.ndarray) -> None:
        values = np.asarray(values, float)
        if values.ndim == 1:
            values = values[:, None]
        n, k = values.shape
        if n == 0:
            return
        self.rec.send_columns(
            path, indexes=[rr.TimeColumn("revolution", sequence=revs), rr.TimeColumn("time", duration=t_s)],
            columns=rr.Scalars.columns(scalars=values.ravel()).partition(np.full(n, k)))

    # -- revolutions: speed, displacement, rotor -------------------------------------------
    def _flush_revolutions(self, final: bool) -> None:
        npr = self.meta.n_probes
        def is_ready(k: int) -> bool:  # its speed is known, and its TOAs are in (or never will be)
            return k + 1 in self._opr and (self._toa_seen.get(k, 0) >= npr or k + 2 in self._opr)

        ready = sorted(k for k in self._pending if final or is_ready(k))
        if not ready:
            return
        revs = np.array(ready, dtype=np.int64)
        t0 = np.array([self._opr[k] for k in ready])
        t_prev = np.array([self._opr.get(k - 1, np.nan) for k in ready])
        t_next = np.array([self._opr.get(k + 1, np.nan) for k in ready])
        missing = ~np.isfinite(t_next)
        if missing.any():  # last revolution(s): extrapolate the previous period
            t_next[missing] = t0[missing] + (t0[missing] - t_prev[missing])
        omega, accel = speed_from_opr(t_prev, t0, t_next)
        nb = self.meta.n_blades
        toa = np.stack([self._toa.pop(k, np.full((nb, npr), np.nan)) for k in ready])
        for k in ready:
            self._pending.discard(k)
            self._toa_seen.pop(k, None)
        self._forget(ready[-1])
        keep = np.isfinite(omega)
        if not keep.all():
            revs, t0, omega, accel, toa = revs[keep], t0[keep], omega[keep], accel[keep], toa[keep]
        if revs.size == 0:
            return
        self.stats["revolutions"] += int(revs.size)
        rpm = omega * 60.0 / TWO_PI
        self._style("speed/rpm", rr.SeriesLines(names="speed (rpm)", colors=[(40, 40, 40)]))
        self._scalars("speed/rpm", revs, t0, rpm)
        if self.meta.engine_orders:
            eo = self.meta.engine_orders[0]
            self._style("speed/eo_freq_hz", rr.SeriesLines(names=f"EO {eo} x speed (Hz)", colors=[_GREY]))
            self._scalars("speed/eo_freq_hz", revs, t0, eo * rpm / 60.0)
        if self._cb_scale is not None:
            self._send_strips("campbell/speed", revs, t0, self._campbell_speed_strips(rpm))
        geom = self._geometry(t0, omega, accel, toa)
        d = btt_displacement(t0, omega, accel, toa, probe_angles_rad=self.meta.probe_angles_rad,
                             blade_angles_rad=geom.blade_angles_rad, opr_angle_rad=self.meta.opr_angle_rad,
                             tip_radius_m=self.meta.tip_radius_m)
        sel = list(self._blades(nb))
        for j in range(npr):
            path = f"{displacement_path(j)}/btt"
            self._style(path, rr.SeriesPoints(names=[f"blade {b} Eq. 1" for b in sel],
                                              colors=_selection_colors(len(sel)),
                                              marker_sizes=[2.0] * len(sel)))
            self._scalars(path, revs, t0, d[:, sel, j] * _MM)
        self._send_strips("rotor/blades", revs, t0, self._rotor_strips(geom, d[:, :, 0]))

    def _forget(self, last: int) -> None:
        """Drop what no revolution still to be logged needs (lost OPRs leave TOAs behind)."""
        oldest = min(self._pending, default=last + 1) - 1
        for k in [k for k in self._toa if k < oldest]:
            del self._toa[k]
            self._toa_seen.pop(k, None)
        if len(self._opr) > 64:
            for k in [k for k in self._opr if k < min(oldest, last) - 1]:
                del self._opr[k]

    def _geometry(self, t0, omega, accel, toa) -> _Geometry:
        """The model's blade angles (set with the metadata), else estimated from these revolutions."""
        if self._geom is None:
            n = min(16, t0.size)
            angles = _estimate_blade_angles(self.meta, t0[:n], omega[:n], accel[:n], toa[:n])
            self._geom = _Geometry(angles, "estimated")
            self._log_rotor_static()
        return self._geom

    def _send_strips(self, path: str, revs, t0, strips: np.ndarray) -> None:
        """``strips`` (n_rev, n_strips, n_points, 2): one row per revolution."""
        n, k = strips.shape[:2]
        columns = rr.LineStrips2D.columns(strips=strips.reshape(n * k, *strips.shape[2:]))
        self.rec.send_columns(
            path, indexes=[rr.TimeColumn("revolution", sequence=revs), rr.TimeColumn("time", duration=t0)],
            columns=columns.partition(np.full(n, k)))

    def _rotor_strips(self, geom: _Geometry, d_m: np.ndarray) -> np.ndarray:
        """Blades at the OPR instant (radius in units of the tip radius), the tip moved
        tangentially by ``exaggeration * d`` (``d`` in m) with a quadratic bending line, shape
        (n_rev, n_blades, 6, 2)."""
        s = np.linspace(0.0, 1.0, 6)
        radius = _HUB_RATIO + (1.0 - _HUB_RATIO) * s
        angle = geom.blade_angles_rad + self.meta.opr_angle_rad  # rotor frame -> space at the OPR
        bend = self.exaggeration * np.nan_to_num(d_m) / self.meta.tip_radius_m
        a = angle[None, :, None] + bend[:, :, None] * (s * s)[None, None, :]
        return _screen(radius[None, None, :], a)

    # -- static parts: rotor furniture, Campbell diagram ---------------------------------------
    def _log_static_run(self) -> None:
        """Casing, probes and OPR sensor (rotor view in units of the tip radius), the model's
        blade angles and the Campbell diagram."""
        meta, rec = self.meta, self.rec
        circle = np.linspace(0.0, TWO_PI, 181)
        rec.log("rotor/casing", rr.LineStrips2D([_screen(_CASING_RATIO, circle), _screen(_HUB_RATIO, circle)],
                                                colors=[_GREY, _GREY], radii=[0.003, 0.003]), static=True)
        pa = meta.probe_angles_rad
        rec.log("rotor/probes", rr.Arrows2D(origins=_screen(1.3, pa), vectors=_screen(0.17, pa + math.pi),
                                            labels=[f"P{j}" for j in range(pa.size)],
                                            colors=[(31, 119, 180)] * pa.size, radii=0.01), static=True)
        opr = [meta.opr_angle_rad]
        rec.log("rotor/opr", rr.Arrows2D(origins=_screen(1.45, opr), vectors=_screen(0.3, [opr[0] + math.pi]),
                                         labels=["OPR"], colors=[(214, 39, 40)], radii=0.015), static=True)
        model = _model_from_meta(meta)
        if model is not None:
            self._geom = _Geometry(model.tip_ref[:, model.nominal_node, 1].copy(), "model")
            self._log_rotor_static()
            self._campbell = model.campbell_freq_hz
        self._log_campbell()

    def _log_rotor_static(self) -> None:
        nb = self.meta.n_blades
        colors = np.tile(np.array([[120, 160, 200]], np.uint8), (nb, 1))
        colors[0] = (230, 120, 20)
        labels = [""] * nb
        labels[0] = "blade 0"
        self.rec.log("rotor/blades", rr.LineStrips2D.from_fields(colors=colors, radii=np.full(nb, 0.013),
                                                                 labels=labels), static=True)

    def _campbell_speed_strips(self, rpm: np.ndarray) -> np.ndarray:
        x_top, _ = self._cb_scale
        x = np.repeat(rpm[:, None] / x_top, 2, axis=1)
        y = np.broadcast_to(np.array([0.0, -_CAMPBELL_HEIGHT]), x.shape)
        return np.stack([x, y], axis=-1)[:, None]

    def _log_campbell(self) -> None:
        """Campbell diagram in a 2-D view: x = speed (rpm), y = frequency (Hz, scaled so that the
        plot box is 1.6 : 1), EO 1..12 lines, the model's family frequencies (constant with
        speed: the model is at zero speed), the run's speed range and the excited crossings."""
        meta = self.meta
        speed = self._speed_range()
        if speed is None:
            return
        lo, hi = speed
        x_step = _nice_ceil(1.1 * hi / 5)
        x_top = math.ceil(1.1 * hi / x_step) * x_step
        f_top = _MAX_EO * x_top / 60.0
        self._cb_scale = (x_top, f_top)

        def pt(rpm, f):  # plot box: x 0..1, y 0..-_CAMPBELL_HEIGHT (up)
            return np.stack(np.broadcast_arrays(np.asarray(rpm, float) / x_top,
                                                -np.asarray(f, float) / f_top * _CAMPBELL_HEIGHT), axis=-1)

        rec, dark, red, green = self.rec, (60, 60, 60), (214, 39, 40), (44, 160, 44)
        small = 1.5e-3
        rec.log("campbell/axes", rr.LineStrips2D([pt([0, x_top], [0, 0]), pt([0, 0], [0, f_top])],
                                                 colors=[dark] * 2, radii=[small] * 2), static=True)
        x_ticks = np.arange(0.0, x_top + 1e-9, x_step)
        f_ticks = np.arange(0.0, f_top + 1e-9, _nice_ceil(f_top / 5))
        rec.log("campbell/ticks", rr.Points2D(
            np.concatenate([pt(x_ticks, -0.05 * f_top), pt(-0.07 * x_top, f_ticks)]),
            labels=[f"{x:g} rpm" for x in x_ticks] + [f"{f:g} Hz" for f in f_ticks],
            radii=small, colors=[dark], show_labels=True), static=True)
        eos = np.arange(1, _MAX_EO + 1)
        x_end = np.minimum(x_top, 60.0 * f_top / eos)
        excited = set(meta.engine_orders)
        eo_colors = [red if e in excited else (170, 170, 170) for e in eos]
        rec.log("campbell/engine_orders", rr.LineStrips2D(
            [pt([0.0, x], [0.0, e * x / 60.0]) for e, x in zip(eos, x_end)], colors=eo_colors,
            radii=[small * (1.5 if e in excited else 0.7) for e in eos]), static=True)
        rec.log("campbell/engine_order_labels", rr.Points2D(
            pt(x_end, 1.02 * eos * x_end / 60.0), labels=[f"EO {e}" for e in eos],
            colors=eo_colors, radii=small, show_labels=True), static=True)
        rec.log("campbell/run_range", rr.Boxes2D(mins=pt([lo], [f_top]), sizes=[[max(hi - lo, 1e-9) / x_top,
                                                                                _CAMPBELL_HEIGHT]],
                                                 colors=[green], radii=small * 0.8), static=True)
        rec.log("campbell/run_label", rr.Points2D(pt(0.5 * (lo + hi), 1.04 * f_top),
                                                  labels=[f"run {lo:g}-{hi:g} rpm"],
                                                  colors=[green], radii=small, show_labels=True), static=True)
        rec.log("campbell/speed", rr.LineStrips2D.from_fields(colors=[green], radii=[small * 1.5]), static=True)
        cb = self._campbell
        if cb is None:
            return
        strips, colors, label_at, labels = [], [], [], []
        for i in range(cb.shape[0]):
            color = _FAMILY_COLORS[i % len(_FAMILY_COLORS)]
            shown = [f for f in cb[i] if 0 < f < f_top]
            for f in shown:
                strips.append(pt([0.0, x_top], [f, f]))
                colors.append(color)
            if shown:
                label_at.append(pt(x_top, max(shown) + 0.03 * f_top))
                labels.append(f"family {i + 1}: {min(shown):.1f}-{max(shown):.1f} Hz")
        if strips:
            rec.log("campbell/families",
                    rr.LineStrips2D(strips, colors=colors, radii=[small * 0.8] * len(strips)), static=True)
            rec.log("campbell/family_labels",
                    rr.Points2D(np.array(label_at), labels=labels, radii=small, colors=[_FAMILY_COLORS[0]],
                                show_labels=True), static=True)
        # resonance crossings of the excited (EO, ND) with each family
        pts, text = [], []
        for eo, nd in zip(meta.engine_orders, meta.nodal_diameters):
            if not 0 <= nd < cb.shape[1]:
                continue
            for i in range(cb.shape[0]):
                f = cb[i, nd]
                rpm = 60.0 * f / eo
                if 0 < f < f_top and rpm <= x_top:
                    pts.append(pt(rpm, f))
                    text.append(f"EO {eo} x ND {nd}: {rpm:.0f} rpm, {f:.1f} Hz")
        if pts:
            rec.log("campbell/resonance", rr.Points2D(np.array(pts), labels=text, radii=small * 5,
                                                      colors=[red], show_labels=True), static=True)

    def _speed_range(self) -> tuple[float, float] | None:
        """(min, max) rpm of the scenario's speed profile (from the metadata's scenario)."""
        from .scenario import scenario_from_dict

        try:
            scn = scenario_from_dict(tomllib.loads(self.meta.scenario_toml), "run metadata scenario")
        except (BttsimError, ValueError, tomllib.TOMLDecodeError):
            return None
        _, rpm = scn.speed.breakpoints()
        return float(rpm.min()), float(rpm.max())

    # -- truth, fits, travelling waves, resonance --------------------------------------------
    def _flush_truth(self) -> None:
        rows, self._truth = self._truth, []
        if not rows:
            return
        self.stats["truth"] += len(rows)
        nb = rows[0].n_blades
        rows = [m for m in rows if m.n_blades == nb]
        revs = np.array([m.header.revolution for m in rows], dtype=np.int64)
        t = np.array([m.header.t_s for m in rows])
        pkpk = np.stack([m.d_eqv_pkpk_m for m in rows]) * _MM
        self._style("truth/amp_pkpk_mm", rr.SeriesLines(names=[f"blade {b} d_eqv" for b in range(nb)],
                                                        colors=[_GREY] * nb, widths=[1.0] * nb))
        self._scalars("truth/amp_pkpk_mm", revs, t, pkpk)
        sel = list(self._blades(nb))
        d_eqv = np.stack([m.d_eqv_m for m in rows]) * _MM  # (n, nb, np)
        for j in range(d_eqv.shape[2]):
            path = f"{displacement_path(j)}/d_eqv"
            self._style(path, rr.SeriesLines(names=[f"blade {b} d_eqv" for b in sel],
                                             colors=_selection_colors(len(sel), light=True),
                                             widths=[1.0] * len(sel)))
            self._scalars(path, revs, t, d_eqv[:, sel, j])

    def _flush_fits(self) -> None:
        rows, self._fits = self._fits, []
        if not rows:
            return
        nb = rows[0].n_blades
        rows = [m for m in rows if m.n_blades == nb]
        self.stats["fits"] += len(rows)
        revs = np.array([m.header.revolution for m in rows], dtype=np.int64)
        t = np.array([m.header.t_s for m in rows])
        names = [f"blade {b}" for b in range(nb)]
        colors = _palette(nb)
        self._style("fit/amp_pkpk_mm", rr.SeriesLines(names=names, colors=colors, widths=[1.5] * nb))
        self._scalars("fit/amp_pkpk_mm", revs, t, np.stack([m.amp_pkpk_m for m in rows]) * _MM)
        self._style("fit/phase_deg", rr.SeriesPoints(names=names, colors=colors, marker_sizes=[1.5] * nb))
        phase = np.rad2deg(np.angle(np.exp(1j * np.stack([m.phase_rad for m in rows]))))
        self._scalars("fit/phase_deg", revs, t, phase)
        self._style("fit/freq_hz", rr.SeriesLines(names="f_BTT (Hz)", colors=[(31, 119, 180)]))
        self._scalars("fit/freq_hz", revs, t, np.array([m.freq_hz for m in rows]))

    def _flush_tw(self, final: bool) -> None:
        rows, self._tw_new = self._tw_new, []
        if rows:
            self.stats["tw"] += len(rows)
            by_probe: dict[int, list] = {}
            for m in rows:
                spec = _signed_spectrum(m.forward_m, m.backward_m) * _MM
                self._tw.setdefault(m.probe, {})[m.header.revolution] = spec.astype(np.float32)
                by_probe.setdefault(m.probe, []).append(m)
                self._tw_max = max(self._tw_max, float(np.nanmax(spec, initial=0.0)))
            for j, ms in sorted(by_probe.items()):
                path = f"tw/dominant_nd/probe_{j}"
                self._style(path, rr.SeriesPoints(names=[f"probe {j}"], marker_sizes=[2.0]))
                revs = np.array([m.header.revolution for m in ms], np.int64)
                nd = np.array([m.dominant_nd for m in ms], float)
                self._scalars(path, revs, np.array([m.header.t_s for m in ms]), nd)
            if self.live:
                self._trim_tw()
        due = time.monotonic() - self._tw_last_log >= self.tw_period_s
        if self._tw and (final or (self.live and rows and due)):
            self._log_tw_matrices()

    def _trim_tw(self) -> None:
        for spectra in self._tw.values():
            if len(spectra) > 2 * self.tw_window:
                last = max(spectra)
                for r in [r for r in spectra if r <= last - self.tw_window]:
                    del spectra[r]

    def _log_tw_matrices(self) -> None:
        """One matrix per probe (signed ND rows x revolution columns, mm); missing revolutions 0."""
        self._tw_last_log = time.monotonic()
        for j, spectra in sorted(self._tw.items()):
            last = max(spectra)
            first = last - self.tw_window + 1 if self.live else min(spectra)
            n_rows = next(iter(spectra.values())).size
            mat = np.zeros((n_rows, last - first + 1), np.float32)
            for r, spec in spectra.items():
                if r >= first and spec.size == n_rows:
                    mat[:, r - first] = spec
            tensor = rr.Tensor(np.nan_to_num(mat), dim_names=["nodal_diameter", "revolution"],
                               value_range=(0.0, self._tw_max or 1.0))
            if self.live:
                self.rec.set_time("revolution", sequence=last)
                self.rec.log(tw_path(j), tensor)
                self.rec.reset_time()
            else:
                self.rec.log(tw_path(j), tensor, static=True)

    def _log_resonance(self, rep: codec.ResonanceReportMsg) -> None:
        static = not self.live
        if not static:
            self.rec.set_time("revolution", sequence=max(rep.header.revolution, 0))
        table = rr.TextDocument(_resonance_markdown(rep), media_type=rr.MediaType.MARKDOWN)
        self.rec.log("resonance/table", table, static=static)
        if rep.blades:
            blade = np.array([b.blade for b in rep.blades], float)
            amp = np.array([b.amp_pkpk_m for b in rep.blades]) * _MM
            self.rec.log("resonance/amp_pkpk_mm/btt", rr.BarChart(amp, abscissa=blade - 0.2, widths=[0.4],
                                                                  color=(31, 119, 180)), static=static)
            if rep.has_truth:
                truth = np.array([b.truth_amp_pkpk_m for b in rep.blades]) * _MM
                bars = rr.BarChart(truth, abscissa=blade + 0.2, widths=[0.4], color=_GREY)
                self.rec.log("resonance/amp_pkpk_mm/d_eqv", bars, static=static)
        if not static:
            self.rec.reset_time()


def _resonance_markdown(rep: codec.ResonanceReportMsg) -> str:
    """The resonance report as a markdown table (amplitudes in mm, frequencies in Hz)."""
    truth = rep.has_truth
    lines = [f"## Resonance: EO {rep.eo}, ND {rep.nd}, condition number {rep.cn:.3g}", ""]
    head = "| blade | amplitude pk-pk (mm) | frequency (Hz) |"
    rule = "|---:|---:|---:|"
    if truth:
        head += " d_eqv amplitude (mm) | d_eqv frequency (Hz) | E_A (%) | E_f (%) |"
        rule += "---:|---:|---:|---:|"
    lines += [head, rule]
    for b in rep.blades:
        row = f"| {b.blade} | {b.amp_pkpk_m * _MM:.4f} | {b.freq_hz:.3f} |"
        if truth:
            row += (f" {b.truth_amp_pkpk_m * _MM:.4f} | {b.truth_freq_hz:.3f} | {b.e_a_pct:.3f} |"
                    f" {b.e_f_pct:.4f} |")
        lines.append(row)
    if truth:
        lines += ["", f"E_A mean {rep.mean_e_a_pct:.3f} %, max {rep.max_e_a_pct:.3f} %; "
                      f"E_f mean {rep.mean_e_f_pct:.4f} %, max {rep.max_e_f_pct:.4f} %"]
    if rep.blades:
        amp = np.array([b.amp_pkpk_m for b in rep.blades]) * _MM
        freq = np.array([b.freq_hz for b in rep.blades])
        lines += ["", f"mean over {len(rep.blades)} blades: {amp.mean():.4f} mm pk-pk at {freq.mean():.3f} Hz"]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------
# Recordings
# --------------------------------------------------------------------------------------


@dataclass(eq=False)
class ViewSession:
    """The result of :func:`log_recording`: the stream (keep it alive while serving), its
    sinks and counts.

    Attributes
    ----------
    recording : rerun.RecordingStream
    sinks : ViewSinks
    stats : dict
        Message counts (``messages``, ``revolutions``, ``fits``, ``tw``, ``truth``, ...).
    elapsed_s : float
        Wall time of reading, decoding and logging.
    """

    recording: rr.RecordingStream
    sinks: ViewSinks
    stats: dict = field(default_factory=dict)
    elapsed_s: float = 0.0

    def wait(self, stop=None, poll_s: float = 0.2) -> None:
        """Keep serving until ``stop`` is truthy (e.g. a :class:`~bttsim_stream.transport.StopFlag`)
        or Ctrl-C."""
        try:
            while not stop:
                time.sleep(poll_s)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        """Flush and disconnect every sink (finalises the ``.rrd``, stops a hosted server)."""
        self.recording.flush()
        self.recording.disconnect()


def log_recording(recording_path, rrd_path=None, *, serve_web: bool = False, web_port: int = 9090,
                  grpc_port: int = 9876, grpc_url: str | None = None, blades: Sequence[int] | None = None,
                  exaggeration: float = DEFAULT_EXAGGERATION) -> ViewSession:
    """Log every view of an MCAP recording to Rerun in one pass.

    Parameters
    ----------
    recording_path : path
        An MCAP recording of the bus (``bttsim simulate``, the recorder node, ``bttsim run``).
    rrd_path : path, optional
        Write an ``.rrd`` file (finalised before returning unless ``serve_web``).
    serve_web : bool
        Host the web viewer on ``web_port`` (gRPC server on ``grpc_port``, loopback); the
        URL is in ``session.sinks.web_url``. Keep the process (and the returned session)
        alive while it is viewed, e.g. ``session.wait(stop)``, then ``session.close()``.
    grpc_url : str, optional
        Also stream to a running viewer.
    blades : sequence of int, optional
        Blades of the raw-displacement views (default 0 and ``n_blades // 2``).
    exaggeration : float
        Tip deflection gain of the rotor view.

    Returns
    -------
    ViewSession

    Raises
    ------
    BttsimError
        Unreadable recording, or no output requested.
    """
    from .io.mcap_io import read_recording

    t_start = time.perf_counter()
    recording = read_recording(recording_path)
    meta = None
    for m in recording.messages:
        if m.key.endswith("/meta"):
            try:
                meta = codec.decode_run_metadata(m.payload, m.key)
                break
            except BttsimError as exc:
                log.warning("skipped run metadata: %s", exc)
    n_probes = meta.n_probes if meta is not None else _probe_count(recording.keys())
    blueprint = build_blueprint(n_probes, n_blades=meta.n_blades if meta else None, live=False)
    rec, sinks = open_recording(rrd_path=rrd_path, grpc_url=grpc_url, serve_web=serve_web, web_port=web_port,
                                grpc_port=grpc_port, blueprint=blueprint,
                                recording_id=meta.run_id if meta is not None else None)
    views = LiveViews(rec, live=False, blades=blades, exaggeration=exaggeration, send_blueprint=False)
    if meta is not None:
        views.feed_message("meta", meta)
    for m in recording.messages:
        if not m.key.endswith("/meta"):
            views.feed(m.key, m.payload)
    views.close()
    session = ViewSession(recording=rec, sinks=sinks, stats=dict(views.stats),
                          elapsed_s=time.perf_counter() - t_start)
    if recording.truncated:
        session.stats["truncated"] = True
    if not serve_web:
        session.close()
    log.info("logged %d messages (%d revolutions) in %.1f s", views.stats["messages"],
             views.stats["revolutions"], session.elapsed_s)
    return session


def _probe_count(topics: Iterable[str]) -> int:
    probes = []
    for k in topics:
        try:
            info = keys.parse_key(k)
        except BttsimError:
            continue
        if info.probe is not None:
            probes.append(info.probe)
    return max(probes, default=0) + 1
