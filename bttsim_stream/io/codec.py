"""Protobuf encoding and decoding of every bus message (the only user of the generated code).

Encoders take numpy arrays and plain values and return serialized bytes (or
:class:`Encoded` triples ``(key, payload, log_time_ns)`` ready to publish or record);
decoders take bytes and return frozen dataclasses holding numpy arrays. The message
definitions are in ``schemas/bttsim/v1/bttsim.proto``; the keys in :mod:`.keys`.

Conventions:

* Per-key sequence numbers: the encoders that publish on a key take ``seqs``, a mutable dict
  ``key -> next seq`` (missing key: 0), and advance it by one per message.
* ``log_time_ns = round(t_s * 1e9)`` with ``t_s`` the header time: the OPR time for
  :class:`bttsim.v1.Opr` and :class:`bttsim.v1.TruthBatch` (the OPR as acquired, so both
  share the revolution's time), the latest TOA of the batch for :class:`bttsim.v1.ToaBatch`.
  MCAP times are unsigned: a negative time is clamped to 0 (``header.t_s`` keeps the value).
* Serialization is deterministic (``SerializeToString(deterministic=True)``): the same input
  gives the same bytes.
* Decoders refuse payloads above :data:`MAX_PAYLOAD_BYTES`, unparsable bytes, a missing
  header, and arrays whose lengths contradict the declared shape, with a one-line
  :class:`~bttsim_stream.errors.BttsimError` naming the key (or the message type).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError

from ..errors import BttsimError
from . import keys as _keys
from ._gen.bttsim.v1 import bttsim_pb2 as _pb

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "PROTO_FILE",
    "Encoded",
    "MsgHeader",
    "OprMsg",
    "ToaBatchMsg",
    "TruthBatchMsg",
    "RunMetadataMsg",
    "BladeFitsMsg",
    "TravellingWaveMsg",
    "BladeResonanceMsg",
    "ResonanceReportMsg",
    "encode_run_metadata",
    "decode_run_metadata",
    "encode_revolutions",
    "decode_opr",
    "decode_toa_batch",
    "decode_truth_batch",
    "encode_blade_fits",
    "decode_blade_fits",
    "encode_travelling_wave",
    "decode_travelling_wave",
    "encode_resonance_report",
    "decode_resonance_report",
    "decode_message",
    "log_time_ns",
    "message_types",
    "schema_name_for",
    "file_descriptor_set",
]

#: Largest payload a decoder accepts, bytes.
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
#: Name of the schema file inside the descriptor (and path under ``schemas/``).
PROTO_FILE = "bttsim/v1/bttsim.proto"
_PACKAGE = "bttsim.v1"
_MAX_NS = (1 << 63) - 1


class Encoded(NamedTuple):
    """One encoded message, ready to ``put`` on the bus or write to MCAP."""

    key: str
    payload: bytes
    log_time_ns: int


@dataclass(frozen=True, slots=True)
class MsgHeader:
    """The header every message carries.

    Attributes
    ----------
    run_id : str
    seq : int
        Per-publisher, per-key sequence number (0, 1, 2, ...).
    revolution : int
        Revolution index, -1 where it does not apply.
    t_s : float
        Simulated time the message refers to, s.
    """

    run_id: str
    seq: int
    revolution: int
    t_s: float


@dataclass(frozen=True, slots=True)
class OprMsg:
    """A decoded :class:`bttsim.v1.Opr`: ``opr_s`` in s, ``opr_ticks`` None if not quantised."""

    header: MsgHeader
    opr_s: float
    opr_ticks: int | None


@dataclass(frozen=True, slots=True, eq=False)
class ToaBatchMsg:
    """A decoded :class:`bttsim.v1.ToaBatch`.

    Attributes
    ----------
    header : MsgHeader
    probe : int
    toa_s : ndarray, shape (n_blades,)
    toa_ticks : ndarray of int64, shape (n_blades,), or None
    """

    header: MsgHeader
    probe: int
    toa_s: np.ndarray
    toa_ticks: np.ndarray | None


@dataclass(frozen=True, slots=True, eq=False)
class TruthBatchMsg:
    """A decoded :class:`bttsim.v1.TruthBatch` (one revolution of ground truth).

    Attributes
    ----------
    header : MsgHeader
    opr_s : float
        Exact OPR time, s.
    omega_mean_rad_s : float
    n_blades, n_probes : int
    toa_s, t_exp_s, d_eqv_m, d_tang_m, d_z_m, d_eq1_m : ndarray, shape (n_blades, n_probes)
    d_eqv_pkpk_m : ndarray, shape (n_blades,)
    """

    header: MsgHeader
    opr_s: float
    omega_mean_rad_s: float
    n_blades: int
    n_probes: int
    toa_s: np.ndarray
    t_exp_s: np.ndarray
    d_eqv_m: np.ndarray
    d_tang_m: np.ndarray
    d_z_m: np.ndarray
    d_eq1_m: np.ndarray
    d_eqv_pkpk_m: np.ndarray


_TRUTH_2D = ("toa_s", "t_exp_s", "d_eqv_m", "d_tang_m", "d_z_m", "d_eq1_m")


@dataclass(frozen=True, slots=True, eq=False)
class RunMetadataMsg:
    """A decoded :class:`bttsim.v1.RunMetadata`: the run's acquisition metadata.

    Attributes
    ----------
    header : MsgHeader
    run_id, rig : str
    n_blades, n_probes, n_revolutions : int
    probe_angles_rad : ndarray, shape (n_probes,)
    probe_axial_m, tip_radius_m, opr_angle_rad : float
    clock_hz, tick_s : float
        TOA clock and its period (both 0 when not quantised).
    stagger_deg : float
    engine_orders, nodal_diameters : tuple of int
    toa_method : str
    duration_s : float
    seed : int
    scenario_toml, software_version : str
    has_truth : bool
    """

    header: MsgHeader
    run_id: str
    rig: str
    n_blades: int
    n_probes: int
    n_revolutions: int
    probe_angles_rad: np.ndarray
    probe_axial_m: float
    tip_radius_m: float
    opr_angle_rad: float
    clock_hz: float
    tick_s: float
    stagger_deg: float
    engine_orders: tuple
    nodal_diameters: tuple
    toa_method: str
    duration_s: float
    seed: int
    scenario_toml: str
    software_version: str
    has_truth: bool

    def to_run_info(self):
        """The same content as a :class:`bttsim_stream.sim.core.RunInfo`."""
        from ..sim.core import RunInfo

        return RunInfo(n_blades=self.n_blades, n_probes=self.n_probes,
                       n_revolutions=self.n_revolutions,
                       probe_angles_rad=self.probe_angles_rad.copy(),
                       probe_axial_m=self.probe_axial_m, tip_radius_m=self.tip_radius_m,
                       opr_angle_rad=self.opr_angle_rad, clock_hz=self.clock_hz,
                       stagger_deg=self.stagger_deg, engine_orders=self.engine_orders,
                       nodal_diameters=self.nodal_diameters, toa_method=self.toa_method,
                       duration_s=self.duration_s, seed=self.seed, rig=self.rig)


@dataclass(frozen=True, slots=True, eq=False)
class BladeFitsMsg:
    """A decoded :class:`bttsim.v1.BladeFits` (one revolution, Eq. 16-17).

    Attributes
    ----------
    header : MsgHeader
    n_blades, engine_order : int
    omega_mean_rad_s : float
    freq_hz : float
        ``f_BTT = EO * Omega / (2 pi)``.
    cn : float
        Condition number of ``B``.
    amp_pkpk_m, phase_rad, dc_m, residual_m, amp_std_m : ndarray, shape (n_blades,)
    """

    header: MsgHeader
    n_blades: int
    engine_order: int
    omega_mean_rad_s: float
    freq_hz: float
    cn: float
    amp_pkpk_m: np.ndarray
    phase_rad: np.ndarray
    dc_m: np.ndarray
    residual_m: np.ndarray
    amp_std_m: np.ndarray


_FIT_ARRAYS = ("amp_pkpk_m", "phase_rad", "dc_m", "residual_m", "amp_std_m")


@dataclass(frozen=True, slots=True, eq=False)
class TravellingWaveMsg:
    """A decoded :class:`bttsim.v1.TravellingWave`.

    Attributes
    ----------
    header : MsgHeader
    probe, n_nd : int
    forward_m, backward_m : ndarray, shape (n_nd,)
        Magnitudes by nodal diameter 0..n_nd-1, m.
    dominant_nd : int
        Largest component; negative for a backward wave.
    """

    header: MsgHeader
    probe: int
    n_nd: int
    forward_m: np.ndarray
    backward_m: np.ndarray
    dominant_nd: int


@dataclass(frozen=True, slots=True)
class BladeResonanceMsg:
    """Resonance of one blade (truth fields meaningful only when ``has_truth``)."""

    blade: int
    amp_pkpk_m: float
    freq_hz: float
    truth_amp_pkpk_m: float
    truth_freq_hz: float
    e_a_pct: float
    e_f_pct: float
    has_truth: bool


@dataclass(frozen=True, slots=True)
class ResonanceReportMsg:
    """A decoded :class:`bttsim.v1.ResonanceReport`.

    Attributes
    ----------
    header : MsgHeader
    nd, eo : int
    cn : float
    blades : tuple of BladeResonanceMsg
    mean_e_a_pct, max_e_a_pct, mean_e_f_pct, max_e_f_pct : float
    """

    header: MsgHeader
    nd: int
    eo: int
    cn: float
    blades: tuple
    mean_e_a_pct: float
    max_e_a_pct: float
    mean_e_f_pct: float
    max_e_f_pct: float

    @property
    def has_truth(self) -> bool:
        """True when every blade carries truth and errors."""
        return bool(self.blades) and all(b.has_truth for b in self.blades)

    def to_summary(self) -> dict:
        """The report in the summary JSON form of the brief (truth fields when present)."""
        blades = []
        for b in self.blades:
            row = {"blade": b.blade, "amp_pkpk_m": b.amp_pkpk_m, "freq_hz": b.freq_hz}
            if b.has_truth:
                row.update(truth_amp_pkpk_m=b.truth_amp_pkpk_m, truth_freq_hz=b.truth_freq_hz,
                           E_A_pct=b.e_a_pct, E_f_pct=b.e_f_pct)
            blades.append(row)
        out = {"nd": self.nd, "eo": self.eo, "cn": self.cn, "blades": blades}
        if self.has_truth:
            out.update(mean_E_A_pct=self.mean_e_a_pct, max_E_A_pct=self.max_e_a_pct,
                       mean_E_f_pct=self.mean_e_f_pct, max_E_f_pct=self.max_e_f_pct)
        return out


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def log_time_ns(t_s: float) -> int:
    """MCAP log time of a message: ``round(t_s * 1e9)`` clamped to ``[0, 2**63 - 1]``."""
    t = float(t_s)
    if not math.isfinite(t):
        return 0 if t != math.inf else _MAX_NS
    return min(max(int(round(t * 1e9)), 0), _MAX_NS)


def _next_seq(seqs: MutableMapping[str, int], key: str) -> int:
    seq = int(seqs.get(key, 0))
    seqs[key] = seq + 1
    return seq


def _fill_header(h, run_id: str, seq: int, revolution: int, t_s: float) -> None:
    h.run_id = run_id
    h.seq = seq
    h.revolution = revolution
    h.t_s = t_s


def _serialize(msg) -> bytes:
    return msg.SerializeToString(deterministic=True)


def _vec(values, name: str, n: int | None = None, dtype=float) -> np.ndarray:
    arr = np.asarray(values, dtype=dtype)
    if arr.ndim != 1 or (n is not None and arr.size != n):
        want = f"({n},)" if n is not None else "1-D"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


def _parse(cls, payload, where: str | None):
    name = cls.DESCRIPTOR.name
    where = where or cls.DESCRIPTOR.full_name
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise BttsimError(f"{where}: {name} payload must be bytes, got {type(payload).__name__}")
    size = len(payload)
    if size > MAX_PAYLOAD_BYTES:
        raise BttsimError(f"{where}: {name} payload of {size} bytes exceeds the "
                          f"{MAX_PAYLOAD_BYTES} byte limit")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except (DecodeError, ValueError, RuntimeError) as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise BttsimError(f"{where}: corrupt {name} ({text})") from None
    if not msg.HasField("header"):
        raise BttsimError(f"{where}: corrupt {name} (no header)")
    return msg, where


def _corrupt(where: str, msg, problem: str) -> BttsimError:
    return BttsimError(f"{where}: corrupt {msg.DESCRIPTOR.name} ({problem})")


def _header(h) -> MsgHeader:
    return MsgHeader(run_id=h.run_id, seq=int(h.seq), revolution=int(h.revolution),
                     t_s=float(h.t_s))


def _array(values, dtype=np.float64) -> np.ndarray:
    return np.array(values, dtype=dtype)


def _check_len(where: str, msg, field: str, n: int, shape: str) -> None:
    got = len(getattr(msg, field))
    if got != n:
        raise _corrupt(where, msg, f"{field} has {got} values, expected {n} for shape {shape}")


def _check_probe_key(where: str, msg, key: str | None, kind: str) -> None:
    if key is None:
        return
    try:
        info = _keys.parse_key(key)
    except BttsimError:
        return
    if info.kind == kind and info.probe != msg.probe:
        raise _corrupt(where, msg, f"probe {msg.probe} on the key of probe {info.probe}")


# --------------------------------------------------------------------------------------
# Schema helpers
# --------------------------------------------------------------------------------------


def message_types() -> tuple[str, ...]:
    """Full names of every message in the schema (``"bttsim.v1.Header"``, ...)."""
    return tuple(d.full_name for d in _pb.DESCRIPTOR.message_types_by_name.values())


def schema_name_for(message_type: str) -> str:
    """The MCAP schema name (full protobuf name) of a message type.

    Parameters
    ----------
    message_type : str
        ``"ToaBatch"`` or ``"bttsim.v1.ToaBatch"``.

    Raises
    ------
    BttsimError
        If the schema has no such message.
    """
    short = message_type.removeprefix(_PACKAGE + ".")
    desc = _pb.DESCRIPTOR.message_types_by_name.get(short)
    if desc is None:
        raise BttsimError(f"unknown message type {message_type!r}")
    return desc.full_name


@functools.lru_cache(maxsize=1)
def file_descriptor_set() -> bytes:
    """The serialized ``FileDescriptorSet`` of ``bttsim/v1/bttsim.proto`` and its dependencies.

    This is the MCAP schema data of every channel (schema encoding ``"protobuf"``).
    """
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(_pb.DESCRIPTOR)
    return fds.SerializeToString(deterministic=True)


# --------------------------------------------------------------------------------------
# Run metadata
# --------------------------------------------------------------------------------------


def encode_run_metadata(info, run_id: str, scenario_toml: str, software_version: str,
                        has_truth: bool, *, seq: int = 0) -> bytes:
    """Encode a run's acquisition metadata (:class:`bttsim.v1.RunMetadata`).

    Parameters
    ----------
    info : RunInfo
        :class:`bttsim_stream.sim.core.RunInfo` (or any object with its attributes).
    run_id : str
    scenario_toml : str
        The run's full scenario file.
    software_version : str
    has_truth : bool
        Whether the run publishes truth on ``bttsim/<rig>/truth``.
    seq : int
        Header sequence number (the queryable answers with the same message: 0).

    Returns
    -------
    bytes
        Payload for the ``bttsim/<rig>/meta`` queryable and recording channel.
    """
    rig = _keys.validate_rig(getattr(info, "rig", "rig1"))
    angles = _vec(info.probe_angles_rad, "probe_angles_rad", int(info.n_probes))
    eos = [int(e) for e in info.engine_orders]
    nds = [int(n) for n in info.nodal_diameters]
    if len(eos) != len(nds):
        raise ValueError("engine_orders and nodal_diameters must have the same length")
    m = _pb.RunMetadata()
    _fill_header(m.header, run_id, int(seq), -1, 0.0)
    clock = float(info.clock_hz)
    m.run_id = run_id
    m.rig = rig
    m.n_blades = int(info.n_blades)
    m.n_probes = int(info.n_probes)
    m.n_revolutions = int(info.n_revolutions)
    m.probe_angles_rad.extend(angles.tolist())
    m.probe_axial_m = float(info.probe_axial_m)
    m.tip_radius_m = float(info.tip_radius_m)
    m.opr_angle_rad = float(info.opr_angle_rad)
    m.clock_hz = clock
    m.tick_s = 1.0 / clock if clock > 0 else 0.0
    m.stagger_deg = float(info.stagger_deg)
    m.engine_orders.extend(eos)
    m.nodal_diameters.extend(nds)
    m.toa_method = str(info.toa_method)
    m.duration_s = float(info.duration_s)
    m.seed = int(info.seed)
    m.scenario_toml = scenario_toml
    m.software_version = software_version
    m.has_truth = bool(has_truth)
    return _serialize(m)


def decode_run_metadata(payload: bytes, key: str | None = None) -> RunMetadataMsg:
    """Decode a :class:`bttsim.v1.RunMetadata` payload.

    Raises
    ------
    BttsimError
        Unparsable, oversized or inconsistent payload (one line, naming ``key``).
    """
    m, where = _parse(_pb.RunMetadata, payload, key)
    _check_len(where, m, "probe_angles_rad", m.n_probes, "(n_probes,)")
    if len(m.engine_orders) != len(m.nodal_diameters):
        raise _corrupt(where, m, f"{len(m.engine_orders)} engine_orders but "
                                 f"{len(m.nodal_diameters)} nodal_diameters")
    if m.n_blades < 1 or m.n_probes < 1:
        raise _corrupt(where, m, f"n_blades = {m.n_blades}, n_probes = {m.n_probes}")
    if m.header.run_id and m.run_id and m.header.run_id != m.run_id:
        raise _corrupt(where, m, f"run_id {m.run_id!r} differs from header {m.header.run_id!r}")
    try:
        _keys.validate_rig(m.rig)
    except BttsimError:
        raise _corrupt(where, m, f"invalid rig name {m.rig!r}") from None
    return RunMetadataMsg(
        header=_header(m.header), run_id=m.run_id or m.header.run_id, rig=m.rig,
        n_blades=int(m.n_blades), n_probes=int(m.n_probes), n_revolutions=int(m.n_revolutions),
        probe_angles_rad=_array(m.probe_angles_rad), probe_axial_m=m.probe_axial_m,
        tip_radius_m=m.tip_radius_m, opr_angle_rad=m.opr_angle_rad, clock_hz=m.clock_hz,
        tick_s=m.tick_s, stagger_deg=m.stagger_deg,
        engine_orders=tuple(int(e) for e in m.engine_orders),
        nodal_diameters=tuple(int(n) for n in m.nodal_diameters), toa_method=m.toa_method,
        duration_s=m.duration_s, seed=int(m.seed), scenario_toml=m.scenario_toml,
        software_version=m.software_version, has_truth=bool(m.has_truth))


# --------------------------------------------------------------------------------------
# Acquisition stream: OPR, TOA batches, truth
# --------------------------------------------------------------------------------------


def encode_revolutions(batch, run_id: str, rig: str, seqs: MutableMapping[str, int], *,
                       include_truth: bool = True) -> list[Encoded]:
    """Encode a :class:`~bttsim_stream.sim.core.RevolutionBatch` into bus messages.

    Per revolution, in this order: one :class:`bttsim.v1.Opr`, one
    :class:`bttsim.v1.ToaBatch` per probe 0..n_probes-1, then one
    :class:`bttsim.v1.TruthBatch` (if ``include_truth``).

    Parameters
    ----------
    batch : RevolutionBatch
        ``revolution`` (n_rev,), ``opr_s`` (n_rev,), ``toa_s`` (n_rev, n_blades, n_probes),
        ``opr_ticks`` / ``toa_ticks`` (same shapes, int64) or None, and ``truth``.
    run_id, rig : str
    seqs : dict
        ``key -> next sequence number``; updated in place (missing keys start at 0).
    include_truth : bool
        False for a run that does not publish truth.

    Returns
    -------
    list of Encoded
        ``(key, payload, log_time_ns)`` in publication order.
    """
    toa = np.asarray(batch.toa_s, dtype=np.float64)
    if toa.ndim != 3:
        raise ValueError(f"toa_s: expected shape (n_rev, n_blades, n_probes), got {toa.shape}")
    nr, nb, npr = toa.shape
    revs = _vec(batch.revolution, "revolution", nr, np.int64)
    opr = _vec(batch.opr_s, "opr_s", nr)
    ticked = batch.toa_ticks is not None
    if ticked != (batch.opr_ticks is not None):
        raise ValueError("opr_ticks and toa_ticks must both be given or both be None")
    if ticked:
        toa_ticks = np.asarray(batch.toa_ticks, dtype=np.int64)
        opr_ticks = _vec(batch.opr_ticks, "opr_ticks", nr, np.int64)
        if toa_ticks.shape != toa.shape:
            raise ValueError(f"toa_ticks: expected shape {toa.shape}, got {toa_ticks.shape}")
        ticks_l = toa_ticks.transpose(0, 2, 1).tolist()
        opr_ticks_l = opr_ticks.tolist()
    k_opr = _keys.opr_key(rig)
    k_toa = [_keys.toa_key(rig, j) for j in range(npr)]
    k_truth = _keys.truth_key(rig)

    # header times, vectorised: OPR time, and the latest TOA of each (revolution, probe)
    latest = np.fmax.reduce(toa, axis=1)  # (nr, np), ignores NaN
    latest = np.where(np.isnan(latest), opr[:, None], latest)
    toa_l = toa.transpose(0, 2, 1).tolist()  # (nr, np, nb) nested lists
    revs_l, opr_l, latest_l = revs.tolist(), opr.tolist(), latest.tolist()

    if include_truth:
        tr = batch.truth
        t2d = {}
        for name in _TRUTH_2D:
            a = np.asarray(getattr(tr, name), dtype=np.float64)
            if a.shape != toa.shape:
                raise ValueError(f"truth.{name}: expected shape {toa.shape}, got {a.shape}")
            t2d[name] = a.reshape(nr, nb * npr).tolist()
        pkpk = np.asarray(tr.d_eqv_pkpk_m, dtype=np.float64)
        if pkpk.shape != (nr, nb):
            raise ValueError(f"truth.d_eqv_pkpk_m: expected shape {(nr, nb)}, got {pkpk.shape}")
        pkpk_l = pkpk.tolist()
        t_opr_l = _vec(tr.opr_s, "truth.opr_s", nr).tolist()
        omega_l = _vec(tr.omega_mean, "truth.omega_mean", nr).tolist()

    out: list[Encoded] = []
    for i in range(nr):
        rev = revs_l[i]
        m = _pb.Opr()
        _fill_header(m.header, run_id, _next_seq(seqs, k_opr), rev, opr_l[i])
        m.opr_s = opr_l[i]
        if ticked:
            m.opr_ticks = opr_ticks_l[i]
            m.has_ticks = True
        out.append(Encoded(k_opr, _serialize(m), log_time_ns(opr_l[i])))
        for j in range(npr):
            t_j = latest_l[i][j]
            m = _pb.ToaBatch()
            _fill_header(m.header, run_id, _next_seq(seqs, k_toa[j]), rev, t_j)
            m.probe = j
            m.toa_s.extend(toa_l[i][j])
            if ticked:
                m.toa_ticks.extend(ticks_l[i][j])
                m.has_ticks = True
            out.append(Encoded(k_toa[j], _serialize(m), log_time_ns(t_j)))
        if include_truth:
            m = _pb.TruthBatch()
            _fill_header(m.header, run_id, _next_seq(seqs, k_truth), rev, opr_l[i])
            m.opr_s = t_opr_l[i]
            m.omega_mean_rad_s = omega_l[i]
            m.n_blades = nb
            m.n_probes = npr
            for name in _TRUTH_2D:
                getattr(m, name).extend(t2d[name][i])
            m.d_eqv_pkpk_m.extend(pkpk_l[i])
            out.append(Encoded(k_truth, _serialize(m), log_time_ns(opr_l[i])))
    return out


def decode_opr(payload: bytes, key: str | None = None) -> OprMsg:
    """Decode a :class:`bttsim.v1.Opr` payload.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header.
    """
    m, where = _parse(_pb.Opr, payload, key)
    if not m.has_ticks and m.opr_ticks != 0:
        raise _corrupt(where, m, "opr_ticks set but has_ticks is false")
    return OprMsg(header=_header(m.header), opr_s=m.opr_s,
                  opr_ticks=int(m.opr_ticks) if m.has_ticks else None)


def decode_toa_batch(payload: bytes, key: str | None = None, *,
                     n_blades: int | None = None) -> ToaBatchMsg:
    """Decode a :class:`bttsim.v1.ToaBatch` payload.

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
    m, where = _parse(_pb.ToaBatch, payload, key)
    n = len(m.toa_s)
    if n == 0:
        raise _corrupt(where, m, "toa_s is empty")
    if n_blades is not None and n != n_blades:
        raise _corrupt(where, m, f"toa_s has {n} values, expected n_blades = {n_blades}")
    if m.has_ticks:
        _check_len(where, m, "toa_ticks", n, "(n_blades,)")
    elif len(m.toa_ticks):
        raise _corrupt(where, m, "toa_ticks set but has_ticks is false")
    _check_probe_key(where, m, key, "toa")
    return ToaBatchMsg(header=_header(m.header), probe=int(m.probe), toa_s=_array(m.toa_s),
                       toa_ticks=_array(m.toa_ticks, np.int64) if m.has_ticks else None)


def decode_truth_batch(payload: bytes, key: str | None = None) -> TruthBatchMsg:
    """Decode a :class:`bttsim.v1.TruthBatch` payload (arrays reshaped to (n_blades, n_probes)).

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m, where = _parse(_pb.TruthBatch, payload, key)
    nb, npr = int(m.n_blades), int(m.n_probes)
    if nb < 1 or npr < 1:
        raise _corrupt(where, m, f"n_blades = {nb}, n_probes = {npr}")
    for name in _TRUTH_2D:
        _check_len(where, m, name, nb * npr, f"({nb}, {npr})")
    _check_len(where, m, "d_eqv_pkpk_m", nb, f"({nb},)")
    arrays = {name: _array(getattr(m, name)).reshape(nb, npr) for name in _TRUTH_2D}
    return TruthBatchMsg(header=_header(m.header), opr_s=m.opr_s,
                         omega_mean_rad_s=m.omega_mean_rad_s, n_blades=nb, n_probes=npr,
                         d_eqv_pkpk_m=_array(m.d_eqv_pkpk_m), **arrays)


# --------------------------------------------------------------------------------------
# Processing outputs
# --------------------------------------------------------------------------------------


def encode_blade_fits(*, run_id: str, rig: str, seqs: MutableMapping[str, int], revolution: int,
                      t_s: float, engine_order: int, omega_mean_rad_s: float, cn: float,
                      amp_pkpk_m, phase_rad, dc_m, residual_m, amp_std_m,
                      freq_hz: float | None = None) -> Encoded:
    """Encode one revolution of blade fits (:class:`bttsim.v1.BladeFits`, key ``fit``).

    Parameters
    ----------
    run_id, rig : str
    seqs : dict
        ``key -> next sequence number``, updated in place.
    revolution : int
    t_s : float
        Time the fit refers to (e.g. the revolution's OPR time), s.
    engine_order : int
    omega_mean_rad_s : float
        Mean speed over the revolution, rad/s.
    cn : float
        Condition number of ``B`` (Eq. 16).
    amp_pkpk_m, phase_rad, dc_m, residual_m, amp_std_m : array_like, shape (n_blades,)
        Peak-to-peak amplitude (m), phase (rad), DC offset (m), fit residual (m) and the
        amplitude's standard deviation (m).
    freq_hz : float, optional
        ``f_BTT``; default ``engine_order * omega_mean_rad_s / (2 pi)`` (Eq. 17).
    """
    amp = _vec(amp_pkpk_m, "amp_pkpk_m")
    nb = amp.size
    arrays = {"amp_pkpk_m": amp}
    for name, values in (("phase_rad", phase_rad), ("dc_m", dc_m), ("residual_m", residual_m),
                         ("amp_std_m", amp_std_m)):
        arrays[name] = _vec(values, name, nb)
    key = _keys.fits_key(rig)
    m = _pb.BladeFits()
    _fill_header(m.header, run_id, _next_seq(seqs, key), int(revolution), float(t_s))
    m.n_blades = nb
    m.engine_order = int(engine_order)
    m.omega_mean_rad_s = float(omega_mean_rad_s)
    m.freq_hz = (float(freq_hz) if freq_hz is not None
                 else int(engine_order) * float(omega_mean_rad_s) / (2.0 * math.pi))
    m.cn = float(cn)
    for name in _FIT_ARRAYS:
        getattr(m, name).extend(arrays[name].tolist())
    return Encoded(key, _serialize(m), log_time_ns(t_s))


def decode_blade_fits(payload: bytes, key: str | None = None) -> BladeFitsMsg:
    """Decode a :class:`bttsim.v1.BladeFits` payload.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m, where = _parse(_pb.BladeFits, payload, key)
    nb = int(m.n_blades)
    for name in _FIT_ARRAYS:
        _check_len(where, m, name, nb, f"({nb},)")
    return BladeFitsMsg(header=_header(m.header), n_blades=nb, engine_order=int(m.engine_order),
                        omega_mean_rad_s=m.omega_mean_rad_s, freq_hz=m.freq_hz, cn=m.cn,
                        **{name: _array(getattr(m, name)) for name in _FIT_ARRAYS})


def encode_travelling_wave(*, run_id: str, rig: str, seqs: MutableMapping[str, int],
                           revolution: int, t_s: float, probe: int, forward_m, backward_m,
                           dominant_nd: int | None = None) -> Encoded:
    """Encode one travelling-wave spectrum (:class:`bttsim.v1.TravellingWave`, key ``tw/<probe>``).

    Parameters
    ----------
    run_id, rig : str
    seqs : dict
        ``key -> next sequence number``, updated in place.
    revolution : int
    t_s : float
    probe : int
    forward_m, backward_m : array_like, shape (n_nd,)
        Forward and backward wave magnitudes by nodal diameter 0..n_nd-1, m.
    dominant_nd : int, optional
        Default: the nodal diameter of the largest magnitude, negative if it is backward
        (forward wins ties).
    """
    fwd = _vec(forward_m, "forward_m")
    bwd = _vec(backward_m, "backward_m", fwd.size)
    if fwd.size == 0:
        raise ValueError("forward_m: at least one nodal diameter is needed")
    if dominant_nd is None:
        f = np.nan_to_num(fwd, nan=-np.inf)
        b = np.nan_to_num(bwd, nan=-np.inf)
        i_f, i_b = int(np.argmax(f)), int(np.argmax(b))
        dominant_nd = -i_b if b[i_b] > f[i_f] else i_f
    key = _keys.tw_key(rig, probe)
    m = _pb.TravellingWave()
    _fill_header(m.header, run_id, _next_seq(seqs, key), int(revolution), float(t_s))
    m.probe = int(probe)
    m.n_nd = fwd.size
    m.forward_m.extend(fwd.tolist())
    m.backward_m.extend(bwd.tolist())
    m.dominant_nd = int(dominant_nd)
    return Encoded(key, _serialize(m), log_time_ns(t_s))


def decode_travelling_wave(payload: bytes, key: str | None = None) -> TravellingWaveMsg:
    """Decode a :class:`bttsim.v1.TravellingWave` payload.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header, or inconsistent array lengths.
    """
    m, where = _parse(_pb.TravellingWave, payload, key)
    n = int(m.n_nd)
    _check_len(where, m, "forward_m", n, f"({n},)")
    _check_len(where, m, "backward_m", n, f"({n},)")
    if abs(m.dominant_nd) >= max(n, 1):
        raise _corrupt(where, m, f"dominant_nd = {m.dominant_nd} with n_nd = {n}")
    _check_probe_key(where, m, key, "tw")
    return TravellingWaveMsg(header=_header(m.header), probe=int(m.probe), n_nd=n,
                             forward_m=_array(m.forward_m), backward_m=_array(m.backward_m),
                             dominant_nd=int(m.dominant_nd))


def _pick(row: Mapping[str, Any], *names: str):
    for name in names:
        if name in row and row[name] is not None:
            return row[name]
    return None


def encode_resonance_report(report: Mapping[str, Any], *, run_id: str, rig: str,
                            seqs: MutableMapping[str, int], revolution: int = -1,
                            t_s: float = 0.0) -> Encoded:
    """Encode a resonance report (:class:`bttsim.v1.ResonanceReport`, key ``resonance``).

    Parameters
    ----------
    report : mapping
        The summary JSON form: ``{"nd", "eo", "cn", "blades": [{"blade", "amp_pkpk_m",
        "freq_hz", ["truth_amp_pkpk_m", "truth_freq_hz", "E_A_pct", "E_f_pct"]}, ...],
        ["mean_E_A_pct", "max_E_A_pct", "mean_E_f_pct", "max_E_f_pct"]}``. A blade row has
        truth when all four truth fields are present (lower-case ``e_a_pct``/``e_f_pct``
        are accepted too).
    run_id, rig : str
    seqs : dict
        ``key -> next sequence number``, updated in place.
    revolution : int
        Last revolution the report covers (-1: the whole run).
    t_s : float
    """
    key = _keys.resonance_key(rig)
    m = _pb.ResonanceReport()
    _fill_header(m.header, run_id, _next_seq(seqs, key), int(revolution), float(t_s))
    m.nd = int(report["nd"])
    m.eo = int(report["eo"])
    m.cn = float(report["cn"])
    for row in report.get("blades", ()):
        b = m.blades.add()
        b.blade = int(row["blade"])
        b.amp_pkpk_m = float(row["amp_pkpk_m"])
        b.freq_hz = float(row["freq_hz"])
        truth = [_pick(row, "truth_amp_pkpk_m"), _pick(row, "truth_freq_hz"),
                 _pick(row, "E_A_pct", "e_a_pct"), _pick(row, "E_f_pct", "e_f_pct")]
        if all(v is not None for v in truth):
            b.truth_amp_pkpk_m, b.truth_freq_hz, b.e_a_pct, b.e_f_pct = map(float, truth)
            b.has_truth = True
    for field, names in (("mean_e_a_pct", ("mean_E_A_pct", "mean_e_a_pct")),
                         ("max_e_a_pct", ("max_E_A_pct", "max_e_a_pct")),
                         ("mean_e_f_pct", ("mean_E_f_pct", "mean_e_f_pct")),
                         ("max_e_f_pct", ("max_E_f_pct", "max_e_f_pct"))):
        value = _pick(report, *names)
        if value is not None:
            setattr(m, field, float(value))
    return Encoded(key, _serialize(m), log_time_ns(t_s))


def decode_resonance_report(payload: bytes, key: str | None = None) -> ResonanceReportMsg:
    """Decode a :class:`bttsim.v1.ResonanceReport` payload.

    Raises
    ------
    BttsimError
        Unparsable or oversized payload, missing header.
    """
    m, where = _parse(_pb.ResonanceReport, payload, key)
    blades = tuple(BladeResonanceMsg(blade=int(b.blade), amp_pkpk_m=b.amp_pkpk_m, freq_hz=b.freq_hz,
                                     truth_amp_pkpk_m=b.truth_amp_pkpk_m,
                                     truth_freq_hz=b.truth_freq_hz, e_a_pct=b.e_a_pct,
                                     e_f_pct=b.e_f_pct, has_truth=bool(b.has_truth))
                   for b in m.blades)
    return ResonanceReportMsg(header=_header(m.header), nd=int(m.nd), eo=int(m.eo), cn=m.cn,
                              blades=blades, mean_e_a_pct=m.mean_e_a_pct,
                              max_e_a_pct=m.max_e_a_pct, mean_e_f_pct=m.mean_e_f_pct,
                              max_e_f_pct=m.max_e_f_pct)


_DECODERS = {
    "bttsim.v1.Opr": decode_opr,
    "bttsim.v1.ToaBatch": decode_toa_batch,
    "bttsim.v1.TruthBatch": decode_truth_batch,
    "bttsim.v1.RunMetadata": decode_run_metadata,
    "bttsim.v1.BladeFits": decode_blade_fits,
    "bttsim.v1.TravellingWave": decode_travelling_wave,
    "bttsim.v1.ResonanceReport": decode_resonance_report,
}


def decode_message(key: str, payload: bytes):
    """Decode a payload by the key it travels on (see :func:`.keys.message_type_for_key`).

    Returns
    -------
    OprMsg, ToaBatchMsg, TruthBatchMsg, RunMetadataMsg, BladeFitsMsg, TravellingWaveMsg or
    ResonanceReportMsg

    Raises
    ------
    BttsimError
        Unknown key, or a payload its decoder refuses.
    """
    return _DECODERS[_keys.message_type_for_key(key)](payload, key)
