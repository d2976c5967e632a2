"""The virtual acquisition stream: scenario -> simulation -> encoded bus messages.

One function, :func:`acquisition_messages`, produces the exact message stream (keys,
payload bytes, log times, sequence numbers) that the simulator node publishes on Zenoh and
that ``bttsim simulate`` writes straight to MCAP, so both are byte-identical. The run id is
derived from the scenario (a hash of its canonical TOML), so the same scenario and seed give
the same bytes every time.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from . import __version__
from .io import codec, keys
from .io.mcap_io import McapRecorder
from .scenario import Scenario, dumps_toml
from .sim.core import RunUpSimulator

__all__ = ["BusMessage", "scenario_run_id", "AcquisitionStream", "simulate_to_mcap"]


@dataclass(frozen=True, slots=True)
class BusMessage:
    """One message for the bus: key expression, protobuf payload, log time (ns), sequence."""

    key: str
    payload: bytes
    log_time_ns: int
    seq: int


def scenario_run_id(scn: Scenario) -> str:
    """Deterministic run id: the first 16 hex digits of the SHA-256 of the scenario's TOML."""
    return hashlib.sha256(dumps_toml(scn).encode()).hexdigest()[:16]


class AcquisitionStream:
    """The run's metadata message and its per-revolution messages.

    Parameters
    ----------
    scn : Scenario
    model : ModalModel, optional
    include_truth : bool
        Publish truth on its own key (a blind run leaves it out).
    run_id : str, optional
        Defaults to :func:`scenario_run_id`.
    chunk_revolutions : int
        Revolutions simulated per batch (pacing granularity).
    n_revolutions : int, optional
        Stop early.
    """

    def __init__(self, scn: Scenario, model=None, *, include_truth: bool = True,
                 run_id: str | None = None, chunk_revolutions: int = 16,
                 n_revolutions: int | None = None) -> None:
        self.scn = scn
        self.sim = RunUpSimulator(scn, model, chunk_revolutions=chunk_revolutions,
                                  n_revolutions=n_revolutions)
        self.info = self.sim.info
        self.rig = scn.run.rig
        self.run_id = run_id or scenario_run_id(scn)
        self.include_truth = include_truth
        self.scenario_toml = dumps_toml(scn)
        self.meta_key = keys.meta_key(self.rig)
        self.meta_payload = codec.encode_run_metadata(self.info, self.run_id, self.scenario_toml,
                                                      __version__, include_truth)

    @property
    def run_metadata_record(self) -> dict:
        return {"run_id": self.run_id, "rig": self.rig, "scenario_toml": self.scenario_toml,
                "software_version": __version__}

    def batches(self) -> Iterator[tuple[object, list[BusMessage]]]:
        """Yield ``(RevolutionBatch, messages)`` chunk by chunk, in publication order."""
        seqs: dict[str, int] = {}
        for batch in self.sim:
            encoded = codec.encode_revolutions(batch, self.run_id, self.rig, seqs,
                                               include_truth=self.include_truth)
            # seqs now holds the next number per key: walk back to number this chunk
            counts: dict[str, int] = {}
            for e in encoded:
                counts[e.key] = counts.get(e.key, 0) + 1
            start = {k: seqs[k] - n for k, n in counts.items()}
            msgs = []
            for e in encoded:
                msgs.append(BusMessage(e.key, e.payload, e.log_time_ns, start[e.key]))
                start[e.key] += 1
            yield batch, msgs


def simulate_to_mcap(scn: Scenario, out: str | Path, *, model=None, include_truth: bool = True,
                     progress=None) -> dict:
    """Write the acquisition stream of ``scn`` straight to an MCAP file (no Zenoh).

    The file holds the ``bttsim.run`` metadata record, the run metadata message on the meta
    key (log time 0) and every OPR / TOA / truth message, exactly as the simulator node
    publishes them. Returns counts.
    """
    stream = AcquisitionStream(scn, model, include_truth=include_truth)
    n = 0
    with McapRecorder(out, run_metadata=stream.run_metadata_record) as rec:
        rec.write(stream.meta_key, stream.meta_payload, 0, sequence=0)
        for batch, msgs in stream.batches():
            for m in msgs:
                rec.write(m.key, m.payload, m.log_time_ns, sequence=m.seq)
            n += len(msgs)
            if progress is not None:
                progress(int(batch.revolution[-1]) + 1, stream.info.n_revolutions)
    return {"run_id": stream.run_id, "messages": n + 1, "revolutions": stream.info.n_revolutions}
