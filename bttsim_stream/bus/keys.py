"""Zenoh key expressions of the bus, and the message type carried on each key.

Every key lives under ``bttsim/<rig>/``; ``<rig>`` names one acquisition system
(``[A-Za-z0-9_-]+``). The table (also in ``schemas/bus.md``):

=================================  ============================  ===============================
key                                message                       notes
=================================  ============================  ===============================
``bttsim/<rig>/opr``               ``bttsim.v1.Opr``             one per revolution
``bttsim/<rig>/toa/<probe>``       ``bttsim.v1.ToaBatch``        one per probe per revolution
``bttsim/<rig>/truth``             ``bttsim.v1.TruthBatch``      ground truth, on its own key
``bttsim/<rig>/signal/<probe>``    ``bttsim.v1.SignalBatch``     raw windows, on request
``bttsim/<rig>/meta``              ``bttsim.v1.RunMetadata``     queryable (and recorded once)
``bttsim/<rig>/fit``               ``bttsim.v1.BladeFits``       one per revolution
``bttsim/<rig>/tw/<probe>``        ``bttsim.v1.TravellingWave``  one per probe per revolution
``bttsim/<rig>/resonance``         ``bttsim.v1.ResonanceReport`` per report
``bttsim/<rig>/nsv``               ``bttsim.v1.NonSynchronous``  per detected block (NSV)
``bttsim/<rig>/alive/<node>``      (none)                        liveliness token of a node
``bttsim/<rig>/ready/<node>``      (none)                        token: has the run metadata
``bttsim/<rig>/done/<node>``       (none)                        token: has the acquisition
``bttsim/<rig>/awaiting/<node>``   (none)                        token: follows the processor
``bttsim/<rig>/reported/<node>``   (none)                        token: has the report
``bttsim/<rig>/status/<node>``     JSON ``bttsim.status.v1``     a node's state and statistics
=================================  ============================  ===============================

A blind processor subscribes to :func:`opr_key` and :func:`toa_all_key` only, so it never
receives truth; a recorder subscribes to :func:`all_key`.
"""

from __future__ import annotations

import functools
import operator
import re
from dataclasses import dataclass

from ..errors import BttsimError

__all__ = [
    "PREFIX",
    "MESSAGE_TYPES",
    "KeyInfo",
    "opr_key",
    "toa_key",
    "toa_all_key",
    "truth_key",
    "signal_key",
    "meta_key",
    "fits_key",
    "tw_key",
    "resonance_key",
    "nsv_key",
    "alive_key",
    "alive_all_key",
    "ready_key",
    "done_key",
    "awaiting_key",
    "reported_key",
    "sent_key",
    "status_key",
    "status_all_key",
    "is_status_key",
    "of_rig",
    "all_key",
    "acquisition_keys",
    "parse_key",
    "message_type_for_key",
    "key_matches",
    "validate_rig",
    "validate_node",
    "ready_all_key",
]

PREFIX = "bttsim"
_NAME_RE = re.compile(r"[A-Za-z0-9_-]+")
_MAX_INDEX = 1 << 16

# kind -> (full protobuf message name or None, takes an index/name chunk)
_KINDS: dict[str, tuple[str | None, bool]] = {
    "opr": ("bttsim.v1.Opr", False),
    "toa": ("bttsim.v1.ToaBatch", True),
    "truth": ("bttsim.v1.TruthBatch", False),
    "signal": ("bttsim.v1.SignalBatch", True),
    "meta": ("bttsim.v1.RunMetadata", False),
    "fit": ("bttsim.v1.BladeFits", False),
    "tw": ("bttsim.v1.TravellingWave", True),
    "resonance": ("bttsim.v1.ResonanceReport", False),
    "nsv": ("bttsim.v1.NonSynchronous", False),
    "alive": (None, True),
    "status": (None, True),  # JSON (bus/status.py), not protobuf
}

#: Full protobuf names of every message type that travels on a key, by key kind.
MESSAGE_TYPES: dict[str, str] = {k: v[0] for k, v in _KINDS.items() if v[0] is not None}


def validate_rig(rig: str) -> str:
    """Return ``rig`` if it is a valid rig name (``[A-Za-z0-9_-]+``), else raise.

    Raises
    ------
    BttsimError
        For an empty name or one with other characters (``/``, ``*``, spaces, ...).
    """
    if not isinstance(rig, str) or not _NAME_RE.fullmatch(rig):
        raise BttsimError(f"invalid rig name {rig!r}: use letters, digits, '_' and '-'")
    return rig


def _index(value, what: str) -> int:
    if isinstance(value, bool):
        raise BttsimError(f"invalid {what} index {value!r}: must be an integer")
    try:
        i = operator.index(value)
    except TypeError:
        raise BttsimError(f"invalid {what} index {value!r}: must be an integer") from None
    if not 0 <= i < _MAX_INDEX:
        raise BttsimError(f"invalid {what} index {i}: must be in 0..{_MAX_INDEX - 1}")
    return i


def opr_key(rig: str) -> str:
    """``bttsim/<rig>/opr``: OPR pulses (:class:`bttsim.v1.Opr`)."""
    return f"{PREFIX}/{validate_rig(rig)}/opr"


def toa_key(rig: str, probe: int) -> str:
    """``bttsim/<rig>/toa/<probe>``: TOA batches of one probe (0-based)."""
    return f"{PREFIX}/{validate_rig(rig)}/toa/{_index(probe, 'probe')}"


def toa_all_key(rig: str) -> str:
    """``bttsim/<rig>/toa/*``: the TOA batches of every probe."""
    return f"{PREFIX}/{validate_rig(rig)}/toa/*"


def truth_key(rig: str) -> str:
    """``bttsim/<rig>/truth``: ground truth (:class:`bttsim.v1.TruthBatch`)."""
    return f"{PREFIX}/{validate_rig(rig)}/truth"


def signal_key(rig: str, probe: int) -> str:
    """``bttsim/<rig>/signal/<probe>``: raw probe windows of one probe (:class:`bttsim.v1.SignalBatch`)."""
    return f"{PREFIX}/{validate_rig(rig)}/signal/{_index(probe, 'probe')}"


def meta_key(rig: str) -> str:
    """``bttsim/<rig>/meta``: the run-metadata queryable (:class:`bttsim.v1.RunMetadata`)."""
    return f"{PREFIX}/{validate_rig(rig)}/meta"


def fits_key(rig: str) -> str:
    """``bttsim/<rig>/fit``: per-revolution blade fits (:class:`bttsim.v1.BladeFits`)."""
    return f"{PREFIX}/{validate_rig(rig)}/fit"


def tw_key(rig: str, probe: int) -> str:
    """``bttsim/<rig>/tw/<probe>``: travelling-wave spectra of one probe."""
    return f"{PREFIX}/{validate_rig(rig)}/tw/{_index(probe, 'probe')}"


def resonance_key(rig: str) -> str:
    """``bttsim/<rig>/resonance``: resonance reports (:class:`bttsim.v1.ResonanceReport`)."""
    return f"{PREFIX}/{validate_rig(rig)}/resonance"


def nsv_key(rig: str) -> str:
    """``bttsim/<rig>/nsv``: non-synchronous vibrations (:class:`bttsim.v1.NonSynchronous`)."""
    return f"{PREFIX}/{validate_rig(rig)}/nsv"


def validate_node(node: str) -> str:
    """Return ``node`` if it is a valid node name (``[A-Za-z0-9_-]+``), else raise
    :class:`BttsimError`."""
    if not isinstance(node, str) or not _NAME_RE.fullmatch(node):
        raise BttsimError(f"invalid node name {node!r}: use letters, digits, '_' and '-'")
    return node


def alive_key(rig: str, node: str) -> str:
    """``bttsim/<rig>/alive/<node>``: liveliness token of a node (no message)."""
    return f"{PREFIX}/{validate_rig(rig)}/alive/{validate_node(node)}"


def _token_key(rig: str, kind: str, node: str) -> str:
    return f"{PREFIX}/{validate_rig(rig)}/{kind}/{validate_node(node)}"


def ready_all_key(rig: str) -> str:
    """``bttsim/<rig>/ready/*``: every node's :func:`ready_key` token."""
    return f"{PREFIX}/{validate_rig(rig)}/ready/*"


def ready_key(rig: str, node: str) -> str:
    """Liveliness token of a node that has the run's metadata (``bttsim/<rig>/ready/<node>``):
    its subscriptions demonstrably reach the publisher, so the simulator may start."""
    return _token_key(rig, "ready", node)


def done_key(rig: str, node: str) -> str:
    """Liveliness token of a node that has received the whole acquisition stream of the run
    (``bttsim/<rig>/done/<node>``): the simulator waits for it before it leaves, since what it
    published is still on its way until then."""
    return _token_key(rig, "done", node)


def awaiting_key(rig: str, node: str) -> str:
    """Liveliness token of a node that follows the processor (``bttsim/<rig>/awaiting/<node>``,
    declared with the run's metadata): it counts the run whole only with the processor's
    resonance report, and the processor waits for its :func:`reported_key` before it leaves."""
    return _token_key(rig, "awaiting", node)


def reported_key(rig: str, node: str) -> str:
    """Liveliness token of a node that has received the processor's resonance report
    (``bttsim/<rig>/reported/<node>``): the processor's last output is in, so it may close
    its session (which drops what is still queued)."""
    return _token_key(rig, "reported", node)


def sent_key(rig: str, node: str) -> str:
    """Liveliness token of a publisher that has published all it will (``bttsim/<rig>/sent/<node>``:
    the simulator's or replay's whole stream, the processor's report) and now only waits for its
    consumers' confirmations: a consumer that follows it and lacks part of the run stops waiting
    for its process to end (which waits for that consumer), and waits only for what may still be
    on its way."""
    return _token_key(rig, "sent", node)


def status_key(rig: str, node: str) -> str:
    """``bttsim/<rig>/status/<node>``: a node's state and final statistics (JSON,
    :mod:`bttsim_stream.bus.status`); never recorded."""
    return f"{PREFIX}/{validate_rig(rig)}/status/{validate_node(node)}"


def status_all_key(rig: str) -> str:
    """``bttsim/<rig>/status/*``: every node's status."""
    return f"{PREFIX}/{validate_rig(rig)}/status/*"


def is_status_key(key: str) -> bool:
    """Is ``key`` a status key (``bttsim/<any>/status/<any>``)? Recorders and views skip them."""
    parts = str(key).split("/")
    return len(parts) == 4 and parts[0] == PREFIX and parts[2] == "status"


def of_rig(messages, rig: str):
    """The messages (anything with a ``key``) of one rig's keys, in their order; a message whose
    key is not a ``bttsim/<rig>/...`` key is kept, for its reader to refuse."""
    for m in messages:
        parts = str(m.key).split("/", 2)
        if len(parts) < 3 or parts[0] != PREFIX or parts[1] == rig:
            yield m


def alive_all_key(rig: str) -> str:
    """``bttsim/<rig>/alive/*``: every node's liveliness token."""
    return f"{PREFIX}/{validate_rig(rig)}/alive/*"


def all_key(rig: str = "*") -> str:
    """``bttsim/<rig>/**``: everything of one rig (``rig="*"``: of every rig)."""
    if rig != "*":
        validate_rig(rig)
    return f"{PREFIX}/{rig}/**"


def acquisition_keys(rig: str) -> tuple[str, str]:
    """The key expressions a blind processor subscribes to: OPR and every probe's TOAs."""
    return opr_key(rig), toa_all_key(rig)


@dataclass(frozen=True, slots=True)
class KeyInfo:
    """A concrete key, parsed.

    Attributes
    ----------
    rig : str
    kind : str
        ``"opr"``, ``"toa"``, ``"truth"``, ``"signal"``, ``"meta"``, ``"fit"``, ``"tw"``,
        ``"resonance"``, ``"nsv"``, ``"alive"`` or ``"status"``.
    probe : int or None
        Probe index for ``toa``, ``signal`` and ``tw`` keys.
    node : str or None
        Node name for ``alive`` and ``status`` keys.
    message_type : str or None
        Full protobuf message name carried on the key (None for liveliness and status keys).
    """

    rig: str
    kind: str
    probe: int | None
    node: str | None
    message_type: str | None


def parse_key(key: str) -> KeyInfo:
    """Parse a concrete key of the bus (a run has few distinct keys: parses are cached).

    Raises
    ------
    BttsimError
        If ``key`` is not one of the keys in the module table (wildcards are not concrete).
    """
    return _parse_key(str(key))


@functools.lru_cache(maxsize=1024)
def _parse_key(key: str) -> KeyInfo:
    parts = key.split("/")
    bad = BttsimError(f"{key}: not a bttsim key (expected {PREFIX}/<rig>/<kind>[/<n>])")
    if len(parts) not in (3, 4) or parts[0] != PREFIX or not _NAME_RE.fullmatch(parts[1]):
        raise bad
    kind = parts[2]
    if kind not in _KINDS:
        raise bad
    message_type, indexed = _KINDS[kind]
    if indexed != (len(parts) == 4):
        raise bad
    probe = node = None
    if indexed:
        last = parts[3]
        if kind in ("alive", "status"):
            if not _NAME_RE.fullmatch(last):
                raise bad
            node = last
        else:
            if not last.isdigit() or (len(last) > 1 and last[0] == "0") or int(last) >= _MAX_INDEX:
                raise bad
            probe = int(last)
    return KeyInfo(rig=parts[1], kind=kind, probe=probe, node=node, message_type=message_type)


def message_type_for_key(key: str) -> str:
    """Full protobuf message name carried on a concrete key, e.g. ``"bttsim.v1.ToaBatch"``.

    Raises
    ------
    BttsimError
        For a key that is not on the bus, or a liveliness key (which carries no message).
    """
    info = parse_key(key)
    if info.message_type is None:
        raise BttsimError(f"{key}: a liveliness or status key carries no protobuf message")
    return info.message_type


def key_matches(expr: str, key: str) -> bool:
    """Whether the concrete ``key`` matches the key expression ``expr``.

    ``*`` matches exactly one chunk, ``**`` zero or more chunks (Zenoh semantics, without
    the ``$*`` sub-chunk wildcard).
    """
    return _match(str(expr).split("/"), str(key).split("/"))


def _match(pat: list[str], parts: list[str]) -> bool:
    if not pat:
        return not parts
    head = pat[0]
    if head == "**":
        return any(_match(pat[1:], parts[i:]) for i in range(len(parts) + 1))
    if not parts:
        return False
    if head == "*" or head == parts[0]:
        return _match(pat[1:], parts[1:])
    return False
