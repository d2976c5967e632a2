"""Rerun views of a BTT run: travelling waves, blade fits, raw BTT displacement, rotor, Campbell, resonance.

This package is the only part of the library that imports :mod:`rerun` (and it never
imports zenoh). It turns decoded bus messages (:mod:`bttsim_stream.bus.codec`) into Rerun
entities in bulk (``send_columns``), either for a whole recording at once
(:func:`log_recording`) or message by message from a live bus (:class:`LiveViews`, flushed
every ``flush_period_s`` while the bus is quiet, every ``busy_flush_period_s`` while busy).

Modules: one per view -- :mod:`.travelling_wave`, :mod:`.fits` (amplitude, phase,
frequency, speed), :mod:`.displacement` (raw Eq. 1 against d_eqv), :mod:`.rotor`,
:mod:`.campbell`, :mod:`.resonance` -- each keeping its own state and logging; then
:mod:`.revolutions` (OPR/TOA to speed and Eq. 1, with the bus's revolution assembler and the
processing's Eq. 1), :mod:`.live` (decoding and dispatch), :mod:`.recording`
(:func:`log_recording`), :mod:`.sinks` (:func:`open_recording`), :mod:`.blueprint` (the
layout, built in one place), :mod:`.paths` (entity paths) and the shared helpers
(``_common``, ``_plot2d``).

Conventions:

* Timelines: ``revolution`` (sequence, the header revolution) and ``time`` (duration, the
  simulated time of the message in s: the OPR time for per-revolution data).
* SI in the code; display units only at logging: mm for displacements and amplitudes,
  degrees for phases, rpm and Hz for speeds and frequencies (the entity path or series
  name says which).
* 2-D views put +x to the right and +y up; angles are anticlockwise from +x, as in the model.
* Plots against speed (the Campbell diagram, amplitude against rpm) are 2-D views whose data
  are logged in their own units (rpm, mm, Hz) under a scaling transform (:mod:`._plot2d`).

``docs/views.md`` lists every entity path and what each view shows. Recordings without
processing messages (a raw acquisition) leave the fit, travelling-wave and resonance views
empty: this package does not fit; ``bttsim view`` runs the processor first.
"""

from .blueprint import build_blueprint
from .live import LiveViews
from .paths import displacement_path, fit_path, fit_rpm_path, tw_path
from .recording import ViewSession, log_recording
from .rotor import DEFAULT_EXAGGERATION
from .sinks import APPLICATION_ID, ViewSinks, finish_files, open_recording

__all__ = [
    "APPLICATION_ID",
    "DEFAULT_EXAGGERATION",
    "ViewSinks",
    "ViewSession",
    "LiveViews",
    "build_blueprint",
    "open_recording",
    "finish_files",
    "log_recording",
    "tw_path",
    "displacement_path",
    "fit_path",
    "fit_rpm_path",
]
