"""The full result's per-revolution fits and spectra of a long run, in scratch files
(:func:`scratch_result`).

With one revolution per fit, every Eq. 16 fit and every travelling-wave spectrum is its own
revolution's: they are computed by blocks of revolutions from the prepared displacements
(read by rows: :class:`~.smoothing.PreparedRows` or :class:`~.history.ScratchRows`) and
written to :class:`~.history.ScratchRows`, read back by rows -- the same numbers as the
whole arrays of :func:`~.span_fits.fit_spans`, :func:`~.travelling_wave.probe_spectra` and
:func:`~.travelling_wave.fit_spectra`, without holding them (``bttsim export`` of a long run).
"""

from __future__ import annotations

import numpy as np

from .displacement import TWO_PI
from .fit import SineFit
from .history import ScratchRows
from .span_fits import fit_rows
from .travelling_wave import TravellingWaveSpectra, fit_spectra, probe_spectra

__all__ = ["SCRATCH_BLOCK", "scratch_result"]

#: Revolutions of prepared displacements read (and fitted, transformed) at once.
SCRATCH_BLOCK = 4096


def scratch_result(d, angles, eos: tuple, joint: bool, omega: np.ndarray, radius: float | None, spans: list,
                   blade_angles_rad, cn: float,
                   block: int | None = None) -> tuple[SineFit, TravellingWaveSpectra, TravellingWaveSpectra]:
    """Every revolution's fits and spectra of the first order, in scratch files.

    Parameters
    ----------
    d : ndarray, PreparedRows or ScratchRows, shape (n_rev, n_blades, n_probes)
        The displacements fitted (prepared, or raw without the preparation), m; read
        ``block`` revolutions at a time (``d[a:b]``).
    angles : ndarray, shape (n_probes,)
        Probe angles, rad.
    eos : tuple of int
        The orders fitted (the spectra are of the first).
    joint : bool
        Whether the orders are fitted jointly.
    omega : ndarray, shape (n_rev,)
        Mean speed per revolution, rad/s.
    radius : float or None
        Tip radius for the fits at the sampling angles inside ``spans`` (None: the probe
        angles everywhere).
    spans : list of (int, int)
        Sorted, non-overlapping ``[start, stop)`` revolutions (the crossings and dwells).
    blade_angles_rad : ndarray, shape (n_blades,), or None
        For :func:`~.travelling_wave.fit_spectra`.
    cn : float
        The fits' condition number (the report's).
    block : int, optional
        Revolutions read at once (default :data:`SCRATCH_BLOCK`).

    Returns
    -------
    fit : SineFit
        Its ``coeffs``, ``amp_pkpk_m``, ``phase_rad``, ``amp_std_m``, ``dc_m``,
        ``residual_rms_m`` and ``n_samples`` are :class:`~.history.ScratchRows` (read by rows);
        ``omega_rad_s`` and ``freq_hz`` arrays. One revolution per fit.
    probe_tw, fit_tw : TravellingWaveSpectra
        Shapes (n_rev, n_probes, n_nd) and (n_rev, n_nd), their magnitudes
        :class:`~.history.ScratchRows`.
    """
    n_rev, nb, npr = d.shape
    n_eo, n_nd = len(eos), nb // 2 + 1
    om = np.asarray(omega, dtype=float)
    step = max(int(block or SCRATCH_BLOCK), 1)
    coeffs = ScratchRows((nb, 1 + 2 * n_eo))
    amp, phase, std = (ScratchRows((nb, n_eo)) for _ in range(3))
    dc, res, n_samples = ScratchRows((nb,)), ScratchRows((nb,)), ScratchRows((nb,), np.int64)
    p_fwd, p_bwd, f_fwd, f_bwd = ScratchRows((npr, n_nd)), ScratchRows((npr, n_nd)), ScratchRows((n_nd,)), \
        ScratchRows((n_nd,))
    for a in range(0, n_rev, step):
        b = min(a + step, n_rev)
        rows = d[a:b]
        near = [(max(s, a) - a, min(e, b) - a) for s, e in spans if s < b and e > a]
        for _, _, f in fit_rows(rows, 0, b - a, angles, eos, joint, om[a:b], radius, near):
            for out, x in ((coeffs, f.coeffs), (amp, f.amp_pkpk_m), (phase, f.phase_rad), (std, f.amp_std_m),
                           (dc, f.dc_m), (res, f.residual_rms_m), (n_samples, f.n_samples)):
                out.write(x)
            tw = fit_spectra(f.coeffs[..., 1] + 1j * f.coeffs[..., 2], eos[0], blade_angles_rad)
            f_fwd.write(tw.forward_m)
            f_bwd.write(tw.backward_m)
        tw = probe_spectra(rows, eos[0])
        p_fwd.write(tw.forward_m)
        p_bwd.write(tw.backward_m)
    fit = SineFit(engine_orders=tuple(eos), window=1, coeffs=coeffs, amp_pkpk_m=amp, phase_rad=phase, amp_std_m=std,
                  dc_m=dc, residual_rms_m=res, n_samples=n_samples, omega_rad_s=om,
                  freq_hz=om[:, None] * np.asarray(eos, float)[None, :] / TWO_PI, cn=cn)
    return (fit, TravellingWaveSpectra(forward_m=p_fwd, backward_m=p_bwd, n_blades=nb),
            TravellingWaveSpectra(forward_m=f_fwd, backward_m=f_bwd, n_blades=nb))
