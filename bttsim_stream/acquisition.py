"""The virtual acquisition stream: scenario -> simulation -> numbered bus messages.

One class, :class:`AcquisitionStream`, produces the exact message stream (keys, payload
bytes, log times, sequence numbers) that the simulator node publishes on Zenoh and that
``bttsim simulate`` writes straight to MCAP, so both are byte-identical. The run id is
derived from the scenario (a hash of its canonical TOML), so the same scenario and seed give
the same bytes every time.
"""

from __future__ import annotations

import hashlib
import itertools
from dataclasses import replace
from pathlib import Path
from typing import Iterator

from . import __version__
from .bus.recording import McapRecorder
from .bus.stream import Message, MessageStream
from .scenario import Scenario, dumps_toml
from .sim.core import RevolutionBatch, RunUpSimulator, collect

__all__ = ["scenario_run_id", "AcquisitionStream", "simulate_to_mcap"]


def scenario_run_id(scenario_toml: str) -> str:
    """Deterministic run id: the first 16 hex digits of the SHA-256 of the scenario's TOML."""
    return hashlib.sha256(scenario_toml.encode()).hexdigest()[:16]


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
    chunk_revolutions : int or None
        Revolutions simulated per batch (pacing granularity); None: the simulator's default.
    n_revolutions : int, optional
        Stop early.

    Attributes
    ----------
    info : RunInfo
        The run metadata as published (run id, scenario, version, truth flag filled in).
    meta : Message
        The run metadata message (sequence 0, log time 0).
    """

    def __init__(self, scn: Scenario, model=None, *, include_truth: bool = True,
                 run_id: str | None = None, chunk_revolutions: int | None = 16,
                 n_revolutions: int | None = None) -> None:
        self.scn = scn
        self.sim = RunUpSimulator(scn, model, chunk_revolutions=chunk_revolutions,
                                  n_revolutions=n_revolutions)
        scenario_toml = dumps_toml(scn)
        self.rig = scn.run.rig
        self.run_id = run_id or scenario_run_id(scenario_toml)
        self.include_truth = include_truth
        self.info = replace(self.sim.info, run_id=self.run_id, scenario_toml=scenario_toml,
                            software_version=__version__, has_truth=bool(include_truth))
        self._stream = MessageStream(self.run_id, self.rig)
        self.meta = self._stream.run_metadata(self.info)

    @property
    def run_metadata_record(self) -> dict:
        """The ``bttsim.run`` MCAP metadata record."""
        return {"run_id": self.run_id, "rig": self.rig, "scenario_toml": self.info.scenario_toml,
                "software_version": __version__}

    def batches(self, group: int = 1) -> Iterator[tuple[RevolutionBatch, list[Message]]]:
        """Yield ``(RevolutionBatch, messages)`` chunk by chunk, in publication order.

        ``group`` simulator chunks are joined into one batch before encoding: the same
        messages (the encoders give the same bytes however revolutions are batched), with
        less per-call overhead where nothing paces the stream (``bttsim simulate``).
        """
        it = iter(self.sim)
        while True:
            chunks = list(itertools.islice(it, max(1, int(group))))
            if not chunks:
                return
            batch = chunks[0] if len(chunks) == 1 else collect(chunks)
            yield batch, self._stream.acquisition(batch, include_truth=self.include_truth)


def simulate_to_mcap(scn: Scenario, out: str | Path, *, model=None, include_truth: bool = True,
                     progress=None) -> dict:
    """Write the acquisition stream of ``scn`` straight to an MCAP file (no Zenoh).

    The file holds the ``bttsim.run`` metadata record, the run metadata message on the meta
    key (log time 0) and every OPR / TOA / truth message, exactly as the simulator node
    publishes them. ``progress(revolutions_done, n_revolutions)`` is called per chunk.
    Returns counts.
    """
    # the simulator's own batch size (its crossings' arrays stay in cache); encoding and MCAP
    # writing take about 64 revolutions at a time
    stream = AcquisitionStream(scn, model, include_truth=include_truth, chunk_revolutions=None)
    n = 0
    with McapRecorder(out, run_metadata=stream.run_metadata_record) as rec:
        rec.write_message(stream.meta)
        for batch, msgs in stream.batches(group=max(1, 64 // stream.sim.chunk)):
            rec.write_all(msgs)
            n += len(msgs)
            if progress is not None:
                progress(int(batch.revolution[-1]) + 1, stream.info.n_revolutions)
    return {"run_id": stream.run_id, "messages": n + 1, "revolutions": stream.info.n_revolutions}
