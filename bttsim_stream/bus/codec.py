"""Protobuf encoding and decoding of every bus message (with :mod:`.codec_base` and
:mod:`.codec_results`, the only user of the generated code).

Each message type maps to one of the library's own frozen dataclasses; there are no
parallel message classes and no dicts:

=============================  ======================================================
``bttsim.v1.RunMetadata``      :class:`~bttsim_stream.sim.core.RunInfo`
``bttsim.v1.Opr``              :class:`OprPulse` (one revolution's part of a
                               :class:`~bttsim_stream.sim.core.RevolutionBatch`)
``bttsim.v1.ToaBatch``         :class:`ToaBatch` (one probe's part of a revolution)
``bttsim.v1.TruthBatch``       :class:`~bttsim_stream.sim.core.Truth` (one revolution)
``bttsim.v1.SignalBatch``      :class:`SignalBatch` (one probe's raw windows of a revolution)
``bttsim.v1.BladeFits``        :class:`~bttsim_stream.process.results.RevolutionFit`
``bttsim.v1.TravellingWave``   :class:`~bttsim_stream.process.travelling_wave.ProbeWave`
``bttsim.v1.ResonanceReport``  :class:`~bttsim_stream.process.resonance.ResonanceReport`
=============================  ======================================================

Encoders take a :class:`Header` (run id, sequence number, revolution, time) and the
dataclass and return the serialized bytes; decoders take bytes and return a
:class:`Decoded` ``(header, body)``. Sequence numbers are not chosen here: the caller owns
them (:class:`bttsim_stream.bus.stream.Sequencer`). The message definitions are in
``schemas/bttsim/v1/bttsim.proto``; the keys in :mod:`.keys`.

Conventions:

* ``log_time_ns = round(t_s * 1e9)`` with ``t_s`` the header time (:func:`log_time_ns`).
  MCAP times are unsigned: a negative time is clamped to 0 (``header.t_s`` keeps the value).
* Serialization is deterministic (``SerializeToString(deterministic=True)``): the same input
  gives the same bytes.
* Decoders refuse payloads above :data:`MAX_PAYLOAD_BYTES`, unparsable bytes, a missing
  header, and arrays whose lengths contradict the declared shape, with a one-line
  :class:`~bttsim_stream.errors.BttsimError` naming the key (or the message type). The run
  metadata must also be physically possible (the limits of :mod:`bttsim_stream.defaults`;
  finite angles in [0, 2 pi), distinct probes, a tip radius > 0, a stagger in (0, 90) deg,
  engine orders in [1, 1000], nodal diameters below the blade count...): every consumer
  computes with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from dataclasses import fields as _dataclass_fields

import numpy as np

from ..defaults import MAX_BLADES, MAX_ENGINE_ORDER, MAX_PROBES, MAX_REVOLUTIONS, MAX_RPM, MAX_SPEEDS
from ..errors import BttsimError
from ..sim.records import RunInfo, Truth
from ..sim.signal import EDGES, TRIGGER_KINDS, RawSignals
from . import keys as _keys
from ._gen.bttsim.v1 import bttsim_pb2 as _pb
from .codec_base import (MAX_PAYLOAD_BYTES, PROTO_FILE, Decoded, Header, as_array, check_len, check_probe_key,
                         corrupt_error, fill_header, header_of, packed_doubles, parse_payload, serialize, as_vector,
                         file_descriptor_set, log_time_ns, schema_name_for)
from .codec_bulk import (assemble, encode_fits, encode_opr_batch, encode_probe_waves, encode_toa_batches, field_tag,
                         header_parts, is_repeated, le_doubles, log_times_ns, packed_field, packed_varints,
                         scalar_field)
from .codec_results import (check_fit, check_probe_wave, decode_fit, decode_nsv, decode_probe_wave,
                            decode_resonance_report, encode_fit, encode_nsv, encode_probe_wave, encode_resonance_report)

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "is_repeated",
    "PROTO_FILE",
    "Header",
    "Decoded",
    "OprPulse",
    "ToaBatch",
    "encode_run_metadata",
    "decode_run_metadata",
    "encode_opr",
    "decode_opr",
    "encode_toa_batch",
    "decode_toa_batch",
    "encode_truth",
    "decode_truth",
    "opr_row",
    "toa_row",
    "truth_row",
    "encode_opr_batch",
    "encode_toa_batches",
    "encode_truth_batch",
    "SignalBatch",
    "MAX_WINDOW_SAMPLES",
    "MAX_EXTRA_EDGES_PER_BLADE",
    "encode_signal_batch",
    "encode_signal_batches",
    "decode_signal_batch",
    "log_times_ns",
    "encode_fit",
    "encode_fits",
    "decode_fit",
    "encode_probe_wave",
    "encode_probe_waves",
    "decode_probe_wave",
    "encode_resonance_report",
    "decode_resonance_report",
    "encode_nsv",
    "decode_nsv",
    "decode_message",
    "Checked",
    "check_message",
    "log_time_ns",
    "schema_name_for",
    "file_descriptor_set",
]

#: Most extra trigger edges (double pulses) a ``ToaBatch`` may carry per blade.
MAX_EXTRA_EDGES_PER_BLADE = 8
#: Most samples a raw-signal window may hold (the scenario allows 4096 at the slowest speed).
MAX_WINDOW_SAMPLES = 1 << 16
#: Largest |first sample index| of a signal window: exact as a float, far from int64 overflow.
MAX_FIRST_SAMPLE = 1 << 52
TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class OprPulse:
    """One OPR pulse (``bttsim.v1.Opr``): ``opr_s`` in s, ``opr_ticks`` None if not quantised."""

    opr_s: float
    opr_ticks: int | None = None


@dataclass(frozen=True, slots=True, eq=False)
class ToaBatch:
    """One probe's TOAs of one revolution (``bttsim.v1.ToaBatch``).

    Attributes
    ----------
    probe : int
    toa_s : ndarray, shape (n_blades,)
    toa_ticks : ndarray of int64, shape (n_blades,), or None
    extra_toa_s : ndarray, shape (n_extra,)
        Trigger edges after the first in a blade's window (double pulses), time order, s.
    extra_toa_ticks : ndarray of int64, shape (n_extra,), or None
    """

    probe: int
    toa_s: np.ndarray
    toa_ticks: np.ndarray | None = None
    extra_toa_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    extra_toa_ticks: np.ndarray | None = None


@dataclass(frozen=True, slots=True, eq=False)
class SignalBatch:
    """One probe's raw windows of one revolution (``bttsim.v1.SignalBatch``).

    Window ``b`` holds the samples ``k = first_sample[b] .. first_sample[b] + n_samples[b] - 1``
    taken at ``t_k = k / sample_rate_hz``; volts ``= range_lo_v + code * lsb_v``.

    Attributes
    ----------
    probe : int
    sample_rate_hz, range_lo_v, lsb_v : float
    bits : int
    trigger : str
    level_v, hysteresis_v : float
    edge : str
    first_sample, n_samples : ndarray of int64, shape (n_blades,)
    codes : ndarray of int64, shape (sum(n_samples),)
        The windows' ADC codes, concatenated in blade order.
    toa_s : ndarray, shape (n_blades,)
        The TOAs published on the probe's TOA key, s (NaN: missing).
    n_edges : ndarray of int64, shape (n_blades,)
    fraction : float
        The constant-fraction trigger's fraction.
    """

    probe: int
    sample_rate_hz: float
    range_lo_v: float
    lsb_v: float
    bits: int
    trigger: str
    level_v: float
    hysteresis_v: float
    edge: str
    first_sample: np.ndarray
    n_samples: np.ndarray
    codes: np.ndarray
    toa_s: np.ndarray
    n_edges: np.ndarray
    fraction: float = 0.5

    def window(self, blade: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample times (s) and volts (V) of one blade's window, each shape (n_samples[blade],)."""
        start = int(self.n_samples[:blade].sum())
        n = int(self.n_samples[blade])
        k = self.first_sample[blade] + np.arange(n)
        return k / self.sample_rate_hz, self.range_lo_v + self.codes[start:start + n] * self.lsb_v


_TRUTH_2D = ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m")
_TRUTH_NUMBERS_2D = tuple(_pb.TruthBatch.DESCRIPTOR.fields_by_name[f].number for f in _TRUTH_2D)
_TRUTH_NUMBER_PKPK = _pb.TruthBatch.DESCRIPTOR.fields_by_name["d_eqv_pkpk_m"].number
_TRUTH_NUMBERS = frozenset((*_TRUTH_NUMBERS_2D, _TRUTH_NUMBER_PKPK))
#: Every field of :class:`~bttsim_stream.sim.core.Truth`, in its order.
_TRUTH_FIELDS = tuple(f.name for f in _dataclass_fields(Truth))


# --------------------------------------------------------------------------------------
# Run metadata
# --------------------------------------------------------------------------------------


def encode_run_metadata(header: Header, info: RunInfo) -> bytes:
    """Encode a run's acquisition metadata (:class:`bttsim.v1.RunMetadata`).

    Parameters
    ----------
    header : Header
        ``revolution`` -1; the simulator and its queryable use ``seq`` 0.
    info : RunInfo
        With ``run_id`` (defaults to the header's), ``scenario_toml``, ``software_version``
        and ``has_truth`` set by the publisher.

    Returns
    -------
    bytes
        Payload for the ``bttsim/<rig>/meta`` queryable and recording channel.
    """
    rig = _keys.validate_rig(info.rig)
    angles = as_vector(info.probe_angles_rad, "probe_angles_rad", int(info.n_probes))
    eos = [int(e) for e in info.engine_orders]
    nds = [int(n) for n in info.nodal_diameters]
    if len(eos) != len(nds):
        raise ValueError("engine_orders and nodal_diameters must have the same length")
    m = _pb.RunMetadata()
    fill_header(m.header, header.run_id, int(header.seq), int(header.revolution), float(header.t_s))
    m.run_id = info.run_id or header.run_id
    m.rig = rig
    m.n_blades = int(info.n_blades)
    m.n_probes = int(info.n_probes)
    m.n_revolutions = int(info.n_revolutions)
    m.probe_angles_rad.extend(angles.tolist())
    m.probe_axial_m = float(info.probe_axial_m)
    m.tip_radius_m = float(info.tip_radius_m)
    m.opr_angle_rad = float(info.opr_angle_rad)
    m.clock_hz = float(info.clock_hz)
    m.tick_s = info.tick_s
    m.stagger_deg = float(info.stagger_deg)
    m.engine_orders.extend(eos)
    m.nodal_diameters.extend(nds)
    m.toa_method = str(info.toa_method)
    m.duration_s = float(info.duration_s)
    m.seed = int(info.seed)
    m.scenario_toml = info.scenario_toml
    m.software_version = info.software_version
    m.has_truth = bool(info.has_truth)
    if info.sensing_angles_rad is not None:
        sensing = as_vector(info.sensing_angles_rad, "sensing_angles_rad", int(info.n_blades))
        m.sensing_angles_rad.extend(sensing.tolist())
    if info.family_freq_hz is not None:
        fam = np.asarray(info.family_freq_hz, dtype=float)
        if fam.ndim != 2 or fam.shape[1] != int(info.n_blades) // 2 + 1:
            raise ValueError(f"family_freq_hz: expected shape (n_families, {int(info.n_blades) // 2 + 1}), "
                             f"got {fam.shape}")
        m.n_families = fam.shape[0]
        m.family_freq_hz.extend(fam.ravel().tolist())
    if (info.family_speed_rad_s is None) != (info.family_freq_hz_at_speed is None):
        raise ValueError("family_speed_rad_s and family_freq_hz_at_speed go together")
    if info.family_speed_rad_s is not None:
        if info.family_freq_hz is None:
            raise ValueError("family_freq_hz_at_speed needs family_freq_hz")
        speeds = as_vector(info.family_speed_rad_s, "family_speed_rad_s")
        at_speed = np.asarray(info.family_freq_hz_at_speed, dtype=float)
        if at_speed.shape != (speeds.size,) + fam.shape:
            raise ValueError(f"family_freq_hz_at_speed: expected shape {(speeds.size,) + fam.shape}, "
                             f"got {at_speed.shape}")
        m.family_speed_rad_s.extend(speeds.tolist())
        m.family_freq_hz_at_speed.extend(at_speed.ravel().tolist())
    m.speed_min_rpm, m.speed_max_rpm = (float(v) for v in info.speed_range_rpm)
    return serialize(m)


#: Highest family frequency at speed a decoder accepts, Hz (far above any bladed-disk mode;
#: keeps ``(2 pi f)^2`` of the interpolation finite).
_MAX_FREQ_HZ = 1e9
#: Smallest step between two of those speeds a decoder accepts, rad/s (the interpolation's
#: divided differences in ``Omega^2`` stay finite).
_MIN_SPEED_STEP_RAD_S = 1e-3


def _run_metadata_problem(m) -> str | None:
    """What makes a parsed ``RunMetadata`` physically impossible (None: nothing). Every
    consumer computes with these values, so a forged or corrupt one is refused here."""
    angles = np.array(m.probe_angles_rad, dtype=float)
    if not np.all((angles >= 0) & (angles < TWO_PI)):
        return f"probe_angles_rad must be finite angles in [0, 2 pi), got {angles.tolist()}"
    if np.unique(angles).size != angles.size:
        return "probe_angles_rad must be distinct"
    for name, lo, hi in (("tip_radius_m", 0.0, None), ("stagger_deg", 0.0, 90.0)):
        v = getattr(m, name)
        if not (math.isfinite(v) and v > lo and (hi is None or v < hi)):
            return f"{name} = {v!r} out of range"
    if not (math.isfinite(m.opr_angle_rad) and 0.0 <= m.opr_angle_rad < TWO_PI):
        return f"opr_angle_rad = {m.opr_angle_rad!r} must be in [0, 2 pi)"
    for name in ("probe_axial_m", "clock_hz", "duration_s", "speed_min_rpm", "speed_max_rpm"):
        v = getattr(m, name)
        if not math.isfinite(v) or (name != "probe_axial_m" and v < 0):
            return f"{name} = {v!r} must be finite" + ("" if name == "probe_axial_m" else " and >= 0")
    if not m.speed_min_rpm <= MAX_RPM or not m.speed_max_rpm <= MAX_RPM:
        return f"speed range {m.speed_min_rpm!r}..{m.speed_max_rpm!r} rpm is above {MAX_RPM:g} rpm"
    if not 1 <= m.n_revolutions <= MAX_REVOLUTIONS:
        return f"n_revolutions = {m.n_revolutions} out of [1, {MAX_REVOLUTIONS}]"
    if m.speed_min_rpm > m.speed_max_rpm:
        return f"speed range {m.speed_min_rpm!r}..{m.speed_max_rpm!r} rpm: the lowest above the highest"
    if not len(m.engine_orders):
        return "no engine order"
    for eo, nd in zip(m.engine_orders, m.nodal_diameters):
        if not 1 <= eo <= MAX_ENGINE_ORDER:
            return f"engine order {eo} out of [1, {MAX_ENGINE_ORDER}]"
        if nd >= m.n_blades:
            return f"nodal diameter {nd} >= n_blades = {m.n_blades}"
    if not np.all(np.isfinite(np.array(m.sensing_angles_rad, dtype=float))):
        return "sensing_angles_rad must be finite"
    if m.n_families > 64:
        return f"n_families = {m.n_families} (at most 64)"
    fam = np.array(m.family_freq_hz, dtype=float)
    if not np.all(np.isfinite(fam) & (fam >= 0)):
        return "family_freq_hz must be finite and >= 0"
    speeds = np.array(m.family_speed_rad_s, dtype=float)
    top = MAX_RPM * TWO_PI / 60.0
    with np.errstate(invalid="ignore"):
        ok = (2 <= speeds.size <= MAX_SPEEDS and speeds[0] == 0.0 and speeds[-1] <= top
              and bool(np.all(np.diff(speeds) >= _MIN_SPEED_STEP_RAD_S)))
    if speeds.size and not ok:
        return (f"family_speed_rad_s must hold 2..{MAX_SPEEDS} speeds ascending from 0 to at most {top:.6g} rad/s "
                f"({MAX_RPM:g} rpm), at least {_MIN_SPEED_STEP_RAD_S:g} rad/s apart")
    if (speeds.size or len(m.family_freq_hz_at_speed)) and not m.n_families:
        return "family_freq_hz_at_speed without family_freq_hz"
    at_speed = np.array(m.family_freq_hz_at_speed, dtype=float)
    if not np.all((at_speed >= 0) & (at_speed <= _MAX_FREQ_HZ)):
        return f"family_freq_hz_at_speed must be finite, >= 0 and <= {_MAX_FREQ_HZ:g} Hz"
    return None


def decode_run_metadata(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.RunMetadata` payload into ``(Header, RunInfo)``.

    Raises
    ------
    BttsimError
        Unparsable, oversized or inconsistent payload (one line, naming ``key``).
    """
    m, where = parse_payload(_pb.RunMetadata, payload, key)
    if not (1 <= m.n_blades <= MAX_BLADES and 1 <= m.n_probes <= MAX_PROBES):
        raise corrupt_error(where, m, f"n_blades = {m.n_blades}, n_probes = {m.n_probes} (1..{MAX_BLADES} blades, "
                                 f"1..{MAX_PROBES} probes)")
    check_len(where, m, "probe_angles_rad", m.n_probes, "(n_probes,)")
    if len(m.engine_orders) != len(m.nodal_diameters):
        raise corrupt_error(where, m, f"{len(m.engine_orders)} engine_orders but "
                                 f"{len(m.nodal_diameters)} nodal_diameters")
    problem = _run_metadata_problem(m)
    if problem:
        raise corrupt_error(where, m, problem)
    if m.header.run_id and m.run_id and m.header.run_id != m.run_id:
        raise corrupt_error(where, m, f"run_id {m.run_id!r} differs from header {m.header.run_id!r}")
    try:
        _keys.validate_rig(m.rig)
    except BttsimError:
        raise corrupt_error(where, m, f"invalid rig name {m.rig!r}") from None
    sensing = None
    if len(m.sensing_angles_rad):
        check_len(where, m, "sensing_angles_rad", m.n_blades, "(n_blades,)")
        sensing = as_array(m.sensing_angles_rad)
    families = None
    if m.n_families:
        n_nd = m.n_blades // 2 + 1
        check_len(where, m, "family_freq_hz", m.n_families * n_nd, f"({m.n_families}, {n_nd})")
        families = as_array(m.family_freq_hz).reshape(m.n_families, n_nd)
    speeds = at_speed = None
    if len(m.family_speed_rad_s) or len(m.family_freq_hz_at_speed):
        n_s = len(m.family_speed_rad_s)
        check_len(where, m, "family_freq_hz_at_speed", n_s * families.size, f"({n_s}, {m.n_families}, {n_nd})")
        speeds = as_array(m.family_speed_rad_s)
        at_speed = as_array(m.family_freq_hz_at_speed).reshape((n_s,) + families.shape)
    info = RunInfo(
        n_blades=int(m.n_blades), n_probes=int(m.n_probes), n_revolutions=int(m.n_revolutions),
        probe_angles_rad=as_array(m.probe_angles_rad), probe_axial_m=m.probe_axial_m,
        tip_radius_m=m.tip_radius_m, opr_angle_rad=m.opr_angle_rad, clock_hz=m.clock_hz,
        stagger_deg=m.stagger_deg, engine_orders=tuple(int(e) for e in m.engine_orders),
        nodal_diameters=tuple(int(n) for n in m.nodal_diameters), toa_method=m.toa_method,
        duration_s=m.duration_s, seed=int(m.seed), rig=m.rig, sensing_angles_rad=sensing,
        family_freq_hz=families, family_speed_rad_s=speeds, family_freq_hz_at_speed=at_speed,
        speed_range_rpm=(m.speed_min_rpm, m.speed_max_rpm),
        run_id=m.run_id or m.header.run_id, scenario_toml=m.scenario_toml,
        software_version=m.software_version, has_truth=bool(m.has_truth))
    return Decoded(header_of(m.header), info)


# --------------------------------------------------------------------------------------
# Acquisition stream: OPR, TOA batches, truth
# --------------------------------------------------------------------------------------


def encode_opr(header: Header, pulse: OprPulse) -> bytes:
    """Encode one OPR pulse (:class:`bttsim.v1.Opr`)."""
    m = _pb.Opr()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.opr_s = pulse.opr_s
    if pulse.opr_ticks is not None:
        m.opr_ticks = pulse.opr_ticks
        m.has_ticks = True
    return serialize(m)


def _check_opr(payload: bytes, key: str | None):
    """The parsed ``Opr`` after every check of :func:`decode_opr`."""
    m, where = parse_payload(_pb.Opr, payload, key)
    if not m.has_ticks and m.opr_ticks != 0:
        raise corrupt_error(where, m, "opr_ticks set but has_ticks is false")
    return m


def decode_opr(payload: bytes, key: str | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.Opr` payload into ``(Header, OprPulse)``.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header.
    """
    m = _check_opr(payload, key)
    return Decoded(header_of(m.header), OprPulse(opr_s=m.opr_s,
                                               opr_ticks=int(m.opr_ticks) if m.has_ticks else None))


def encode_toa_batch(header: Header, probe: int, toa_s: list, toa_ticks: list | None = None,
                     extra_toa_s=(), extra_toa_ticks=None) -> bytes:
    """Encode one probe's TOAs of one revolution (:class:`bttsim.v1.ToaBatch`).

    ``toa_s`` (and ``toa_ticks``) are sequences of n_blades values (lists are fastest);
    ``extra_toa_s`` (and ``extra_toa_ticks`` when ticked) the later edges of double pulses.
    """
    m = _pb.ToaBatch()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.probe = probe
    m.toa_s.extend(toa_s)
    if toa_ticks is not None:
        m.toa_ticks.extend(toa_ticks)
        m.has_ticks = True
    m.extra_toa_s.extend(np.asarray(extra_toa_s, dtype=np.float64).tolist())
    if toa_ticks is not None and len(m.extra_toa_s):
        if extra_toa_ticks is None:  # the decoder would refuse the message
            raise ValueError("ticked TOAs with extra edges need their extra_toa_ticks")
        m.extra_toa_ticks.extend(np.asarray(extra_toa_ticks, dtype=np.int64).tolist())
    return serialize(m)


def _check_ticks(where: str, m, name: str, n: int, shape: str) -> None:
    """A ticks field: ``n`` values with ``has_ticks``, none without."""
    if m.has_ticks:
        check_len(where, m, name, n, shape)
    elif len(getattr(m, name)):
        raise corrupt_error(where, m, f"{name} set but has_ticks is false")


def _check_toa(payload: bytes, key: str | None, n_blades: int | None = None) -> tuple:
    """The parsed ``ToaBatch`` and its extra edge times after every check of
    :func:`decode_toa_batch`."""
    m, where = parse_payload(_pb.ToaBatch, payload, key)
    n = len(m.toa_s)
    if n == 0:
        raise corrupt_error(where, m, "toa_s is empty")
    if n_blades is not None and n != n_blades:
        raise corrupt_error(where, m, f"toa_s has {n} values, expected n_blades = {n_blades}")
    _check_ticks(where, m, "toa_ticks", n, "(n_blades,)")
    n_extra = len(m.extra_toa_s)
    if n_extra > MAX_EXTRA_EDGES_PER_BLADE * n:
        raise corrupt_error(where, m,
                            f"{n_extra} extra edges for {n} blades (at most {MAX_EXTRA_EDGES_PER_BLADE} a blade)")
    _check_ticks(where, m, "extra_toa_ticks", n_extra, "(n_extra,)")
    extra = as_array(m.extra_toa_s)
    if n_extra and not np.isfinite(extra).all():
        raise corrupt_error(where, m, "an extra edge time is not finite")
    check_probe_key(where, m, key, "toa")
    return m, extra


def decode_toa_batch(payload: bytes, key: str | None = None, *, n_blades: int | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.ToaBatch` payload into ``(Header, ToaBatch)``.

    Parameters
    ----------
    payload : bytes
    key : str, optional
        The key it came on (named in errors; its probe index must match the message's).
    n_blades : int, optional
        Expected blade count (from the run metadata).

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m, extra = _check_toa(payload, key, n_blades)
    return Decoded(header_of(m.header), ToaBatch(
        probe=int(m.probe), toa_s=as_array(m.toa_s),
        toa_ticks=as_array(m.toa_ticks, np.int64) if m.has_ticks else None, extra_toa_s=extra,
        extra_toa_ticks=as_array(m.extra_toa_ticks, np.int64) if m.has_ticks else None))


def encode_truth(header: Header, truth: Truth, i: int = 0) -> bytes:
    """Encode revolution ``i`` of a :class:`~bttsim_stream.sim.core.Truth` (:class:`bttsim.v1.TruthBatch`)."""
    toa = truth.toa_s[i]
    nb, npr = toa.shape
    m = _pb.TruthBatch()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.opr_s = float(truth.opr_s[i])
    m.omega_mean_rad_s = float(truth.omega_mean[i])
    m.n_blades = nb
    m.n_probes = npr
    for name in _TRUTH_2D:
        getattr(m, name).extend(np.asarray(getattr(truth, name)[i], dtype=np.float64).ravel().tolist())
    m.d_eqv_pkpk_m.extend(np.asarray(truth.d_eqv_pkpk_m[i], dtype=np.float64).tolist())
    _fill_nsv(m, truth, i)
    if truth.eo_pkpk_m is not None:
        m.eo_engine_order.extend(np.asarray(truth.eo_engine_order[i], dtype=np.int64).tolist())
        m.eo_pkpk_m.extend(np.asarray(truth.eo_pkpk_m[i], dtype=np.float64).ravel().tolist())
    return serialize(m)


def _decode_eo(where: str, m, nb: int) -> dict:
    """``eo_engine_order`` (1, n_eo) and ``eo_pkpk_m`` (1, n_blades, n_eo) of one revolution
    after size and range checks (n_eo = 0 for a recording made before the fields existed)."""
    k = len(m.eo_engine_order)
    if k > MAX_ENGINE_ORDER:
        raise corrupt_error(where, m, f"{k} eo_engine_order entries, more than {MAX_ENGINE_ORDER}")
    check_len(where, m, "eo_pkpk_m", nb * k, f"({nb}, {k})")
    listed = list(m.eo_engine_order)  # a few values: Python compares them faster than numpy
    if k and not (1 <= listed[0] and listed[-1] <= MAX_ENGINE_ORDER and all(map(int.__lt__, listed, listed[1:]))):
        raise corrupt_error(where, m, f"eo_engine_order must ascend strictly within [1, {MAX_ENGINE_ORDER}]")
    orders = np.array(listed, np.int64)
    amp = as_array(m.eo_pkpk_m).reshape(1, nb, k)
    if amp.size and not (amp.min() >= 0 and amp.max() < math.inf):  # a NaN fails the first test
        raise corrupt_error(where, m, "eo_pkpk_m values must be finite and >= 0")
    return {"eo_engine_order": orders.reshape(1, k), "eo_pkpk_m": amp}


#: Largest number of non-synchronous components a TruthBatch may carry.
MAX_NSV_COMPONENTS = 64
_NSV_KINDS = ("rotating_stall", "flutter", "broadband")


def _fill_nsv(m, truth: Truth, i: int) -> None:
    """The ``nsv`` components of revolution ``i`` (none when the truth has none)."""
    if truth.nsv_kind is None:
        return
    for j in range(truth.nsv_kind.shape[1]):
        c = m.nsv.add()
        c.kind = str(truth.nsv_kind[i, j])
        c.freq_hz = float(truth.nsv_freq_hz[i, j])
        c.nodal_diameter = int(truth.nsv_nd[i, j])
        c.amp_pkpk_m = float(truth.nsv_amp_pkpk_m[i, j])
        c.rms_m = float(truth.nsv_rms_m[i, j])
        c.band_lo_hz, c.band_hi_hz = (float(x) for x in truth.nsv_band_hz[i, j])


def _decode_nsv(where: str, m, nb: int) -> dict:
    """``nsv_*`` arrays of one revolution, shape (1, k) (k = 0 for a run without NSV, and for
    recordings made before the field existed), after size and range checks."""
    k = len(m.nsv)
    if k > MAX_NSV_COMPONENTS:
        raise corrupt_error(where, m, f"{k} nsv components, more than {MAX_NSV_COMPONENTS}")
    kind, nd = [], []
    vals = np.zeros((5, k))
    for j, c in enumerate(m.nsv):
        if c.kind not in _NSV_KINDS:
            raise corrupt_error(where, m, f"nsv[{j}].kind = {c.kind[:40]!r} (expected one of {', '.join(_NSV_KINDS)})")
        v = (c.freq_hz, c.amp_pkpk_m, c.rms_m, c.band_lo_hz, c.band_hi_hz)
        if not all(math.isfinite(x) and x >= 0 for x in v) or c.band_lo_hz > c.band_hi_hz:
            raise corrupt_error(where, m, f"nsv[{j}] values must be finite and >= 0 with band_lo_hz <= band_hi_hz")
        if abs(c.nodal_diameter) > nb:
            raise corrupt_error(where, m, f"nsv[{j}].nodal_diameter = {c.nodal_diameter}, beyond the {nb} blades")
        kind.append(c.kind)
        nd.append(int(c.nodal_diameter))
        vals[:, j] = v
    return {"nsv_kind": np.array(kind, dtype="<U14").reshape(1, k), "nsv_freq_hz": vals[0:1],
            "nsv_nd": np.array(nd, np.int64).reshape(1, k), "nsv_amp_pkpk_m": vals[1:2], "nsv_rms_m": vals[2:3],
            "nsv_band_hz": vals[3:5].T.reshape(1, k, 2).copy()}


def _check_truth(payload: bytes, key: str | None) -> tuple:
    """The parsed ``TruthBatch`` and its ``nsv_*`` and ``eo_*`` arrays after every check of
    :func:`decode_truth`."""
    m, where = parse_payload(_pb.TruthBatch, payload, key)
    nb, npr = int(m.n_blades), int(m.n_probes)
    if nb < 1 or npr < 1:
        raise corrupt_error(where, m, f"n_blades = {nb}, n_probes = {npr}")
    for name in _TRUTH_2D:
        check_len(where, m, name, nb * npr, f"({nb}, {npr})")
    check_len(where, m, "d_eqv_pkpk_m", nb, f"({nb},)")
    if not (math.isfinite(m.opr_s) and math.isfinite(m.omega_mean_rad_s) and m.omega_mean_rad_s > 0):
        raise corrupt_error(where, m,
                            f"opr_s = {m.opr_s!r}, omega_mean_rad_s = {m.omega_mean_rad_s!r} (finite, speed > 0)")
    return m, _decode_nsv(where, m, nb), _decode_eo(where, m, nb)


def decode_truth(payload: bytes, key: str | None = None, *, fields=None) -> Decoded:
    """Decode a :class:`bttsim.v1.TruthBatch` payload into ``(Header, Truth)`` with one
    revolution (arrays of shape (1, n_blades, n_probes), (1, n_blades) and (1,)).

    ``fields``: the per-probe fields (``toa_s``, ``t_exp_s``, ``d_eqv_m``, ``d_tang_m``,
    ``d_z_m``, ``d_eq1_m``) to build (default all; the others are None, e.g. for a consumer
    that scores against the peak-to-peak envelope only). The checks are the same whatever it
    keeps: a payload is refused, or not, for the same reasons.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m, nsv, eo = _check_truth(payload, key)
    kept = _TRUTH_2D if fields is None else tuple(n for n in _TRUTH_2D if n in fields)
    arrays = _truth_arrays(payload, m, kept)
    truth = Truth(opr_s=np.array([m.opr_s]), omega_mean=np.array([m.omega_mean_rad_s]),
                  **{name: arrays.get(name) for name in (*_TRUTH_2D, "d_eqv_pkpk_m")}, **nsv, **eo)
    return Decoded(header_of(m.header), truth)


def _truth_arrays(payload: bytes, m, kept: tuple) -> dict:
    """The envelope ``d_eqv_pkpk_m`` (shape (1, n_blades)) and the per-probe fields ``kept``
    (shape (1, n_blades, n_probes)) of a checked ``TruthBatch`` ``m`` (:func:`_check_truth`)."""
    nb, npr = int(m.n_blades), int(m.n_probes)
    numbers = frozenset((_TRUTH_NUMBER_PKPK, *(k for n, k in zip(_TRUTH_2D, _TRUTH_NUMBERS_2D) if n in kept)))
    # the lengths are checked; without a per-probe field the envelope alone is read through
    # protobuf's container (one field: walking the payload would cost more)
    raw = (packed_doubles(bytes(payload), numbers) if kept else None) or {}
    out = {name: (raw[k] if k in raw else as_array(getattr(m, name))).reshape(1, nb, npr)
           for name, k in zip(_TRUTH_2D, _TRUTH_NUMBERS_2D) if name in kept}
    k = _TRUTH_NUMBER_PKPK
    out["d_eqv_pkpk_m"] = (raw[k] if k in raw else as_array(m.d_eqv_pkpk_m)).reshape(1, nb)
    return out


def opr_row(payload: bytes, key: str | None = None) -> tuple[str, int, float]:
    """``(run_id, revolution, opr_s)`` of a :class:`bttsim.v1.Opr` payload: every check of
    :func:`decode_opr` (the same errors for the same payloads), no dataclass built (a reader
    of a whole recording, :func:`bttsim_stream.offline.load_run`)."""
    m = _check_opr(payload, key)
    h = m.header
    return h.run_id, int(h.revolution), m.opr_s


def toa_row(payload: bytes, key: str | None = None) -> tuple[str, int, int, np.ndarray, np.ndarray]:
    """``(run_id, revolution, probe, toa_s, extra_toa_s)`` of a :class:`bttsim.v1.ToaBatch`
    payload: every check of :func:`decode_toa_batch` (the same errors for the same payloads)
    and the same two arrays, without its dataclasses or the tick arrays."""
    m, extra = _check_toa(payload, key)
    h = m.header
    return h.run_id, int(h.revolution), int(m.probe), as_array(m.toa_s), extra


def truth_row(payload: bytes, key: str | None = None, *, fields=None) -> tuple[str, int, tuple[int, int], dict]:
    """``(run_id, revolution, (n_blades, n_probes), arrays)`` of a :class:`bttsim.v1.TruthBatch`
    payload: every check of :func:`decode_truth` (the same errors for the same payloads), and
    ``arrays`` the :class:`~bttsim_stream.sim.core.Truth` fields ``fields`` (default all) with
    the values, shapes and dtypes :func:`decode_truth` gives them, without building the others
    (a per-probe field not asked for is not read from the payload at all)."""
    m, nsv, eo = _check_truth(payload, key)
    names = _TRUTH_FIELDS if fields is None else tuple(n for n in _TRUTH_FIELDS if n in fields)
    arrays = {"opr_s": np.array([m.opr_s]), "omega_mean": np.array([m.omega_mean_rad_s]), **nsv, **eo,
              **_truth_arrays(payload, m, tuple(n for n in _TRUTH_2D if n in names))}
    return (m.header.run_id, int(m.header.revolution), (int(m.n_blades), int(m.n_probes)),
            {name: arrays[name] for name in names})


# --------------------------------------------------------------------------------------
# Raw probe signals
# --------------------------------------------------------------------------------------


def encode_signal_batch(header: Header, batch: SignalBatch) -> bytes:
    """Encode one probe's raw windows of one revolution (:class:`bttsim.v1.SignalBatch`)."""
    m = _pb.SignalBatch()
    fill_header(m.header, header.run_id, header.seq, header.revolution, header.t_s)
    m.probe = int(batch.probe)
    m.sample_rate_hz, m.range_lo_v, m.lsb_v = float(batch.sample_rate_hz), float(batch.range_lo_v), float(batch.lsb_v)
    m.bits, m.trigger, m.edge = int(batch.bits), batch.trigger, batch.edge
    m.level_v, m.hysteresis_v, m.fraction = float(batch.level_v), float(batch.hysteresis_v), float(batch.fraction)
    m.first_sample.extend(np.asarray(batch.first_sample, dtype=np.int64).tolist())
    m.n_samples.extend(np.asarray(batch.n_samples, dtype=np.int64).tolist())
    m.codes.extend(np.asarray(batch.codes, dtype=np.int64).tolist())
    m.toa_s.extend(np.asarray(batch.toa_s, dtype=np.float64).tolist())
    m.n_edges.extend(np.asarray(batch.n_edges, dtype=np.int64).tolist())
    return serialize(m)


def encode_signal_batches(run_id: str, seq, revolution, t_s, raw: RawSignals, toa_s, n_edges) -> list[bytes]:
    """Every probe's :class:`bttsim.v1.SignalBatch` of a batch of revolutions, in
    ``(revolution, probe)`` order (the same bytes as :func:`encode_signal_batch` one at a time).

    Parameters
    ----------
    run_id : str
    seq, revolution, t_s : array_like, shape (n_rev * n_probes,)
        Header of each message, in ``(revolution, probe)`` order.
    raw : RawSignals
        Windows of the batch's passages, ``(revolution, blade, probe)`` order.
    toa_s, n_edges : ndarray, shape (n_rev, n_blades, n_probes)
        The published TOAs and the trigger's edge counts.
    """
    nr, nb, npr = np.shape(toa_s)
    order = np.arange(nr * nb * npr).reshape(nr, nb, npr).transpose(0, 2, 1).ravel()  # (rev, probe, blade)
    first = raw.first_sample[order].reshape(nr * npr, nb)
    n_samp = raw.n_samples[order].reshape(nr * npr, nb)
    codes = raw.codes[:, order]
    valid = np.arange(codes.shape[0])[:, None] < n_samp.ravel()[None, :]
    flat = codes.T[valid.T]  # windows concatenated in (revolution, probe, blade) order
    ends = np.cumsum(n_samp.sum(axis=1))
    starts = ends - n_samp.sum(axis=1)
    toa = np.asarray(toa_s, dtype=np.float64).transpose(0, 2, 1).reshape(nr * npr, nb)
    edges = np.asarray(n_edges, dtype=np.int64).transpose(0, 2, 1).reshape(nr * npr, nb)
    seq, revolution, t_s = (np.asarray(a).ravel().tolist() for a in (seq, revolution, t_s))
    out = []
    for i in range(nr * npr):
        j = i % npr
        out.append(encode_signal_batch(Header(run_id, seq[i], revolution[i], t_s[i]), SignalBatch(
            probe=j, sample_rate_hz=raw.sample_rate_hz, range_lo_v=raw.range_lo_v, lsb_v=raw.lsb_v, bits=raw.bits,
            trigger=raw.trigger[j], level_v=raw.level_v, hysteresis_v=raw.hysteresis_v, edge=raw.edge,
            first_sample=first[i], n_samples=n_samp[i], codes=flat[starts[i]:ends[i]], toa_s=toa[i],
            n_edges=edges[i], fraction=raw.fraction)))
    return out


def decode_signal_batch(payload: bytes, key: str | None = None, *, n_blades: int | None = None) -> Decoded:
    """Decode a :class:`bttsim.v1.SignalBatch` payload into ``(Header, SignalBatch)``.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, inconsistent lengths, a window longer
        than :data:`MAX_WINDOW_SAMPLES`, codes outside ``[0, 2^bits - 1]``, a non-finite sample
        rate or one below 1 Hz, a non-positive or non-finite code size, an ADC range that
        overflows a float, an unknown trigger or edge.
    """
    m, where = parse_payload(_pb.SignalBatch, payload, key)
    n = len(m.first_sample)
    if n == 0:
        raise corrupt_error(where, m, "first_sample is empty")
    if n_blades is not None and n != n_blades:
        raise corrupt_error(where, m, f"first_sample has {n} values, expected n_blades = {n_blades}")
    for name in ("n_samples", "toa_s", "n_edges"):
        check_len(where, m, name, n, "(n_blades,)")
    n_samp = as_array(m.n_samples, np.int64)
    if n_samp.min() < 1 or n_samp.max() > MAX_WINDOW_SAMPLES:
        raise corrupt_error(where, m, f"n_samples must be in [1, {MAX_WINDOW_SAMPLES}]")
    check_len(where, m, "codes", int(n_samp.sum()), "(sum(n_samples),)")
    if not 1 <= m.bits <= 31:
        raise corrupt_error(where, m, f"bits = {m.bits} (1..31)")
    codes = as_array(m.codes, np.int64)
    if codes.size and codes.max() >= (1 << m.bits):
        raise corrupt_error(where, m, f"an ADC code above 2^{m.bits} - 1")
    first = as_array(m.first_sample, np.int64)  # negative: a window opened before t = 0
    if np.abs(first).max() > MAX_FIRST_SAMPLE:  # sample indices stay exact as floats, and never wrap
        raise corrupt_error(where, m, "first_sample beyond +-2^52")
    # an ADC samples at >= 1 Hz: a window's times (and its plot) stay finite
    if not (math.isfinite(m.sample_rate_hz) and m.sample_rate_hz >= 1.0):
        raise corrupt_error(where, m, f"sample_rate_hz = {m.sample_rate_hz!r} (finite, >= 1)")
    if not (math.isfinite(m.lsb_v) and m.lsb_v > 0):
        raise corrupt_error(where, m, f"lsb_v = {m.lsb_v!r} (finite, > 0)")
    for name in ("range_lo_v", "level_v", "hysteresis_v"):
        if not math.isfinite(getattr(m, name)):
            raise corrupt_error(where, m, f"{name} = {getattr(m, name)!r} (finite)")
    span = ((1 << m.bits) - 1) * m.lsb_v
    if not (math.isfinite(span) and math.isfinite(m.range_lo_v + span)):
        raise corrupt_error(where, m, f"ADC range {m.range_lo_v!r} + (2^{m.bits} - 1) * {m.lsb_v!r} V is not finite")
    if not 0.0 <= m.fraction <= 1.0:
        raise corrupt_error(where, m, f"fraction = {m.fraction!r} (in [0, 1])")
    if m.trigger not in TRIGGER_KINDS or m.edge not in EDGES:
        raise corrupt_error(where, m, f"trigger {m.trigger!r}, edge {m.edge!r}")
    check_probe_key(where, m, key, "signal")
    return Decoded(header_of(m.header), SignalBatch(
        probe=int(m.probe), sample_rate_hz=m.sample_rate_hz, range_lo_v=m.range_lo_v, lsb_v=m.lsb_v, bits=int(m.bits),
        trigger=m.trigger, level_v=m.level_v, hysteresis_v=m.hysteresis_v, edge=m.edge, first_sample=first,
        n_samples=n_samp, codes=codes, toa_s=as_array(m.toa_s), n_edges=as_array(m.n_edges, np.int64),
        fraction=m.fraction))


def encode_truth_batch(run_id: str, seq, revolution, t_s, truth: Truth) -> list[bytes]:
    """:func:`encode_truth` of every revolution of ``truth`` at once (the same bytes).

    Parameters
    ----------
    seq, revolution : array_like of int, shape (n_rev,)
    t_s : array_like of float, shape (n_rev,)
        Header times.
    truth : Truth
        Arrays of n_rev revolutions.
    """
    toa = np.asarray(truth.toa_s)
    n, nb, npr = toa.shape
    parts = header_parts(run_id, np.asarray(seq), revolution, t_s)
    parts += scalar_field(field_tag(_pb.TruthBatch, "opr_s"), truth.opr_s, "double")
    parts += scalar_field(field_tag(_pb.TruthBatch, "omega_mean_rad_s"), truth.omega_mean, "double")
    parts += scalar_field(field_tag(_pb.TruthBatch, "n_blades"), np.full(n, nb), "int")
    parts += scalar_field(field_tag(_pb.TruthBatch, "n_probes"), np.full(n, npr), "int")
    for name in (*_TRUTH_2D, "d_eqv_pkpk_m"):
        values = le_doubles(np.asarray(getattr(truth, name)).reshape(n, -1))
        parts += packed_field(field_tag(_pb.TruthBatch, name), values)
    out = assemble(parts)
    if truth.nsv_kind is not None and truth.nsv_kind.shape[1]:
        for i in range(n):  # the nsv components, appended (protobuf fields concatenate)
            m = _pb.TruthBatch()
            _fill_nsv(m, truth, i)
            out[i] = out[i] + m.SerializeToString(deterministic=True)
    if truth.eo_pkpk_m is not None and np.shape(truth.eo_engine_order)[1]:  # fields 14-15, after nsv (13)
        amp = le_doubles(np.asarray(truth.eo_pkpk_m).reshape(n, -1))
        tail = assemble(packed_varints(field_tag(_pb.TruthBatch, "eo_engine_order"), np.asarray(truth.eo_engine_order))
                         + packed_field(field_tag(_pb.TruthBatch, "eo_pkpk_m"), amp))
        out = [a + b for a, b in zip(out, tail)]
    return out


_DECODERS = {
    "bttsim.v1.Opr": decode_opr,
    "bttsim.v1.ToaBatch": decode_toa_batch,
    "bttsim.v1.SignalBatch": decode_signal_batch,
    "bttsim.v1.TruthBatch": decode_truth,
    "bttsim.v1.RunMetadata": decode_run_metadata,
    "bttsim.v1.BladeFits": decode_fit,
    "bttsim.v1.TravellingWave": decode_probe_wave,
    "bttsim.v1.ResonanceReport": decode_resonance_report,
    "bttsim.v1.NonSynchronous": decode_nsv,
}


def decode_message(key: str, payload: bytes) -> Decoded:
    """Decode a payload by the key it travels on (see :func:`.keys.message_type_for_key`).

    Raises
    ------
    BttsimError
        Unknown key, or a payload its decoder refuses.
    """
    return _DECODERS[_keys.message_type_for_key(key)](payload, key)


@dataclass(frozen=True, slots=True)
class Checked:
    """What a receiver that keeps payloads as they came (a recorder) needs of a message it
    checked: its header, its blade count and its OPR time (:func:`check_message`).

    Attributes
    ----------
    header : Header
    n_blades : int
        ``ToaBatch``: the values of ``toa_s``; ``TruthBatch``: ``n_blades``; else -1.
    opr_s : float
        ``Opr``: the pulse time, s; else 0.
    decoded : Decoded or None
        The whole message where it was decoded (the types :func:`check_message` has no
        cheaper check for: run metadata, signals, reports).
    """

    header: Header
    n_blades: int = -1
    opr_s: float = 0.0
    decoded: Decoded | None = None

    @classmethod
    def of(cls, decoded: Decoded) -> "Checked":
        """The :class:`Checked` of a decoded message (what :func:`check_message` gives)."""
        body = decoded.body
        if isinstance(body, ToaBatch):
            return cls(decoded.header, int(body.toa_s.size), decoded=decoded)
        if isinstance(body, Truth):
            return cls(decoded.header, int(np.shape(body.d_eqv_pkpk_m)[-1]), decoded=decoded)
        if isinstance(body, OprPulse):
            return cls(decoded.header, opr_s=body.opr_s, decoded=decoded)
        return cls(decoded.header, decoded=decoded)


def _checked_opr(payload: bytes, key: str) -> Checked:
    m = _check_opr(payload, key)
    return Checked(header_of(m.header), opr_s=m.opr_s)


def _checked_toa(payload: bytes, key: str) -> Checked:
    m, _ = _check_toa(payload, key)
    return Checked(header_of(m.header), len(m.toa_s))


def _checked_truth(payload: bytes, key: str) -> Checked:
    m, _, _ = _check_truth(payload, key)
    return Checked(header_of(m.header), int(m.n_blades))


_CHECKERS = {
    "bttsim.v1.Opr": _checked_opr,
    "bttsim.v1.ToaBatch": _checked_toa,
    "bttsim.v1.TruthBatch": _checked_truth,
    "bttsim.v1.BladeFits": lambda payload, key: Checked(header_of(check_fit(payload, key).header)),
    "bttsim.v1.TravellingWave": lambda payload, key: Checked(header_of(check_probe_wave(payload, key).header)),
}


def check_message(key: str, payload: bytes) -> Checked:
    """Check a payload as :func:`decode_message` does -- the same
    :class:`~bttsim_stream.errors.BttsimError` for exactly the same payloads, every check of
    its decoder made -- without building its body where that can be skipped (the acquisition
    stream, fits, travelling waves: about half the decoding's CPU).

    Raises
    ------
    BttsimError
        Unknown key, or a payload its decoder refuses.
    """
    message_type = _keys.message_type_for_key(key)
    check = _CHECKERS.get(message_type)
    if check is None:
        return Checked.of(_DECODERS[message_type](payload, key))
    return check(payload, key)
