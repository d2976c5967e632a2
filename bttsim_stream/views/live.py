"""Live views: decode bus messages, hand each to the views that show it, flush them in batches.

:class:`LiveViews` is only a dispatcher: each view (one module each) keeps its own state
and does its own ``send_columns`` logging when flushed. Nothing is shown before the run
metadata arrives (the views need its geometry, speed range and Campbell families);
messages that come earlier are held until then.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import rerun as rr

from ..bus import codec, keys
from ..bus.stream import SequenceTracker
from ..errors import BttsimError
from ..process.options import ProcessOptions, engine_orders_of
from ._common import ViewOutput
from .blueprint import build_blueprint
from .campbell import CampbellView
from .displacement import DisplacementView, selected_blades
from .fits import FitsView, SpeedView
from .nsv import NsvView
from .resonance import ResonanceView
from .revolutions import RevolutionDisplacements
from .rotor import DEFAULT_EXAGGERATION, RotorView
from .signal import SignalView
from .travelling_wave import TravellingWaveView

__all__ = ["Incoming", "MessageDecoder", "LiveViews"]

log = logging.getLogger("bttsim.views")
_MAX_EARLY = 1 << 16  # messages held while waiting for the run metadata
#: The flush period while messages keep coming, in flush periods of a quiet bus.
BUSY_FLUSH_FACTOR = 5.0


@dataclass(frozen=True, slots=True)
class Incoming:
    """A decoded message with its key's kind (``"opr"``, ``"fit"``...) and rig."""

    kind: str
    rig: str
    decoded: codec.Decoded


class MessageDecoder:
    """Keys and payloads to :class:`Incoming` messages; counts what it skips.

    A key that is not a message (a liveliness token...) is ``ignored``, as is a sample
    already received (a late joiner's history repeating a live sample: its sequence number
    is below the key's next); a payload that does not decode is ``bad`` (the first three
    are logged).
    """

    def __init__(self, *, log_bad: bool = True) -> None:
        self.log_bad = log_bad  # False where a bad payload is an error of its own (a recording file)
        self.ignored = 0
        self.bad = 0
        self.first_bad: str | None = None  # why the first bad payload was refused
        self._seqs = SequenceTracker()
        self._keys: dict[str, keys.KeyInfo | None] = {}  # a bus has few keys: parse each once

    def decode(self, key: str, payload: bytes) -> Incoming | None:
        """The message, or None (counted as ignored or bad)."""
        info = self._keys.get(key, False)
        if info is False:
            try:
                info = keys.parse_key(key)
            except BttsimError:
                info = None
            self._keys[key] = info
        if info is None or info.message_type is None:
            self.ignored += 1
            return None
        try:
            decoded = codec.decode_message(key, payload)
        except BttsimError as exc:
            self.bad += 1
            self.first_bad = self.first_bad or str(exc)
            if self.log_bad and self.bad <= 3:
                log.warning("skipped a message: %s", exc)
            return None
        if not self._seqs.accept(key, decoded.header.seq):  # history already received live
            self.ignored += 1
            return None
        return Incoming(info.kind, info.rig, decoded)


@dataclass(eq=False)
class _Views:
    revolutions: RevolutionDisplacements
    speed: SpeedView
    displacement: DisplacementView
    rotor: RotorView
    campbell: CampbellView
    fits: FitsView
    tw: TravellingWaveView
    resonance: ResonanceView
    signal: SignalView
    nsv: NsvView


class LiveViews:
    """Turn bus messages into Rerun views, batched into ``send_columns`` calls.

    Feed messages in bus order with :meth:`feed` (key and payload) or :meth:`feed_decoded`;
    when ``live`` the views are flushed every ``flush_period_s`` while the bus is quiet
    (:meth:`poll` between messages) and every ``busy_flush_period_s`` while messages keep
    coming (checked on each feed: a viewer catching up with a fast run sends fewer, larger
    ``send_columns`` batches, the same rows); and on :meth:`close`.

    Parameters
    ----------
    recording : rerun.RecordingStream
        With its sinks set (:func:`~bttsim_stream.views.open_recording`).
    live : bool
        True: travelling waves as a rolling window of ``tw_window`` revolutions re-logged at
        most every ``tw_period_s``, resonance reports as they come. False (a whole recording,
        flushed once on close): whole-run travelling-wave matrices and the last resonance
        report, static.
    blades : sequence of int, optional
        Blades of the displacement views (default 0 and ``n_blades // 2``).
    exaggeration : float
        Tip deflection gain of the rotor view.
    flush_period_s, tw_window, tw_period_s : float, int, float
    busy_flush_period_s : float, optional
        The flush period while messages keep coming (default ``5 * flush_period_s``).
    send_blueprint : bool
        Send :func:`~bttsim_stream.views.build_blueprint` when the run metadata arrives,
        and again if fits of an engine order it lacks arrive (not needed when the sinks
        were opened with the blueprint as the default).
    engine_orders : sequence of int, optional
        Engine orders of that blueprint (default: what the processor fits by default for
        the run, i.e. the metadata's).
    decoder : MessageDecoder, optional
        The decoder of :meth:`feed`, whose counts go into :attr:`stats` (give the one that
        decoded what is fed with :meth:`feed_decoded`).
    signal_probe : int
        Probe of the raw signal view (shown for the first of ``blades``) when the bus
        carries raw signals; its tab joins the layout when the first one arrives.

    Attributes
    ----------
    meta : RunInfo or None
        The run shown.
    stats : dict
        Counts: ``messages`` (decoded), ``ignored``, ``bad``, ``revolutions`` (shown),
        ``fits``, ``tw``, ``truth``, ``resonance``, ``signal`` (raw windows shown).

    Notes
    -----
    A revolution's speed, raw displacement and rotor frame come once the next revolution
    is in (:mod:`.revolutions`); :meth:`close` shows the last one with an extrapolated speed.
    """

    def __init__(self, recording: rr.RecordingStream, *, live: bool = True, blades: Sequence[int] | None = None,
                 exaggeration: float = DEFAULT_EXAGGERATION, flush_period_s: float = 0.2, tw_window: int = 256,
                 tw_period_s: float = 1.0, send_blueprint: bool = True,
                 engine_orders: Sequence[int] | None = None, decoder: MessageDecoder | None = None,
                 signal_probe: int = 0, busy_flush_period_s: float | None = None) -> None:
        self.rec = recording
        self.out = ViewOutput(recording, live)
        self.live = bool(live)
        self.flush_period_s = float(flush_period_s)
        self.busy_flush_period_s = BUSY_FLUSH_FACTOR * self.flush_period_s if busy_flush_period_s is None \
            else float(busy_flush_period_s)
        self._options = {"blades": blades, "exaggeration": float(exaggeration), "tw_window": int(tw_window),
                         "tw_period_s": float(tw_period_s)}
        self._send_blueprint = bool(send_blueprint)
        self.signal_probe = int(signal_probe)
        self._signal_shown = False
        self._nsv_shown = False
        self._eos = None if engine_orders is None else [int(e) for e in engine_orders]
        self.decoder = decoder or MessageDecoder()
        self.meta = None
        self._views: _Views | None = None
        self._early: list[Incoming] = []
        self._messages = 0
        self._ignored = 0
        self._revolutions = 0
        self._last_flush = time.monotonic()
        self._closed = False

    @property
    def stats(self) -> dict:
        v = self._views
        views = {"fits": v.fits.count["fits"], "tw": v.tw.count, "truth": v.fits.count["truth"],
                 "resonance": v.resonance.count, "signal": v.signal.count} if v else dict.fromkeys(
            ("fits", "tw", "truth", "resonance", "signal"), 0)
        return {"messages": self._messages, "ignored": self.decoder.ignored + self._ignored, "bad": self.decoder.bad,
                "revolutions": self._revolutions, **views}

    # -- input ---------------------------------------------------------------------------
    def feed(self, key: str, payload: bytes) -> None:
        """Decode and take one message (what does not decode is counted and skipped)."""
        msg = self.decoder.decode(key, payload)
        if msg is not None:
            self.feed_decoded(msg)

    def feed_decoded(self, msg: Incoming) -> None:
        """Take one decoded message."""
        self._messages += 1
        if msg.kind == "meta":
            self._on_meta(msg.decoded.body)
        elif self._views is None:
            if len(self._early) < _MAX_EARLY:
                self._early.append(msg)
            else:
                self._ignored += 1
        else:
            self._route(msg)
        self.poll(busy=True)

    def _on_meta(self, meta) -> None:
        if self.meta is not None:
            if meta.run_id != self.meta.run_id:
                log.warning("ignoring run %s: already showing run %s", meta.run_id, self.meta.run_id)
            return
        self.meta = meta
        out, o = self.out, self._options
        shown = RevolutionDisplacements(meta)
        self._views = _Views(
            revolutions=shown, speed=SpeedView(out), displacement=DisplacementView(out, meta, o["blades"]),
            rotor=RotorView(out, meta, shown.blade_angles_rad, o["exaggeration"]), campbell=CampbellView(out, meta),
            fits=FitsView(out, meta), tw=TravellingWaveView(out, window=o["tw_window"], period_s=o["tw_period_s"]),
            resonance=ResonanceView(out),
            signal=SignalView(out, meta, self.signal_probe, (selected_blades(meta.n_blades, o["blades"]) or (0,))[0]),
            nsv=NsvView(out))
        if self._eos is None:
            self._eos = list(engine_orders_of(meta, ProcessOptions()))
        if self._send_blueprint:
            self._blueprint()
        early, self._early = self._early, []
        for msg in early:
            self._route(msg)

    def _blueprint(self) -> None:
        self.rec.send_blueprint(build_blueprint(self.meta.n_probes, n_blades=self.meta.n_blades,
                                                engine_orders=self._eos, live=self.live,
                                                signal_probe=self.signal_probe if self._signal_shown else None,
                                                non_synchronous=self._nsv_shown))

    def _show_nsv(self) -> None:
        """The first non-synchronous vibration: the layout gains its tab."""
        if not self._nsv_shown:
            self._nsv_shown = True
            if self._send_blueprint:
                log.info("non-synchronous vibration reported: layout updated")
                self._blueprint()

    def _route(self, msg: Incoming) -> None:
        """Hand a message to the views that show it."""
        if msg.rig != self.meta.rig or msg.decoded.header.run_id != self.meta.run_id:  # another run's
            self._ignored += 1
            return
        v, kind, d = self._views, msg.kind, msg.decoded
        if kind in ("opr", "toa"):
            v.revolutions.add(kind, d)
        elif kind == "truth":
            v.displacement.add_truth(d)
            v.fits.add_truth(d)
        elif kind == "fit":
            v.fits.add(d)
        elif kind == "tw":
            v.tw.add(d)
        elif kind == "resonance":
            v.resonance.add(d)
            if d.body.non_synchronous:
                self._show_nsv()
                v.nsv.add_report(d.body)
        elif kind == "nsv":
            self._show_nsv()
            v.nsv.add(d)
        elif kind == "signal":
            if not self._signal_shown:
                self._signal_shown = True
                if self._send_blueprint:
                    log.info("raw signals on the bus: layout updated")
                    self._blueprint()
            v.signal.add(d)

    # -- output --------------------------------------------------------------------------
    def poll(self, *, busy: bool = False) -> bool:
        """Flush if ``flush_period_s`` (``busy``: ``busy_flush_period_s``, more messages are
        coming) has passed since the last flush (live only)."""
        period = self.busy_flush_period_s if busy else self.flush_period_s
        if self.live and time.monotonic() - self._last_flush >= period:
            self.flush()
            return True
        return False

    def flush(self, *, final: bool = False) -> None:
        """Send everything buffered that can be shown now (``final``: all of it)."""
        self._last_flush = time.monotonic()
        v = self._views
        if v is None:
            return
        rows = v.revolutions.pop(final)
        if rows is not None:
            self._revolutions += len(rows)
            for view in (v.speed, v.displacement, v.rotor, v.campbell):
                view.update(rows)
        for view in (v.displacement, v.fits, v.tw, v.resonance, v.signal, v.nsv):
            view.flush(final)
        new = [e for e in v.fits.engine_orders if e not in self._eos]
        if new:
            self._eos += new
            if self._send_blueprint:
                log.info("fits of engine order(s) %s: layout updated", new)
                self._blueprint()

    def close(self) -> None:
        """Flush everything (the last revolution with an extrapolated speed) and the stream."""
        if self._closed:
            return
        self._closed = True
        if self._views is None and self._early:
            log.warning("no run metadata received: %d message(s) not shown", len(self._early))
        self.flush(final=True)
        self.rec.flush()
