"""95 % intervals of each blade's resonant amplitude, frequency and phase, and the notes that
say what limits them.

Every crossing's per-blade estimate (:mod:`.methods`) gets ``amp_ci95_m``, ``freq_ci95_hz``
and ``phase_ci95_rad`` (``[lo, hi]``). The interval is built from the data only (the truth is
never used: it only validates, ``bench/bench_intervals.py``). Amplitudes are peak-to-peak, m.

Amplitude half-width (conservative sum of the bias bounds on top of the root-sum-square of
the random terms)::

    h_A = 1.96 sqrt(s_noise^2 + s_layout^2) + D_model + b_zero

``s_noise`` (a)
    The method's residual-noise standard error: ``amp_std_m`` of :mod:`.methods` (the
    least-squares covariance ``s^2 (B^T B)^-1`` of Eq. 16, where the layout's conditioning
    enters, or the revolution-to-revolution scatter times the smoother's noise gain). For the
    CFF its covariance also holds the response's change inside the window (a model misfit,
    counted by ``D_model``): the scatter of the unsmoothed per-revolution amplitudes over
    ``sqrt(w)`` is used instead.
``s_layout`` (a, layout)
    Unmodelled per-probe content (sampling-angle harmonics, other modes, probe position
    errors), :data:`MODEL_ERROR` of the response's amplitude per probe, amplified by the
    layout: ``sqrt(g_AA) MODEL_ERROR A`` with ``g_AA = u^T (B^T B)^-1 u`` the inverse normal
    matrix of Eq. 16 along the response's direction ``u``. Negligible for a well-conditioned
    layout (``sqrt(g_AA)`` about ``sqrt(2 / n_probes)``), dominant when CN is large (residuals
    cannot show it: a 3-probe fit has none).
``D_model`` (b, e)
    The method's own bias (the sweep rate and the smoothing flatten the swept peak for
    ``peak``; the window for ``cff``; the SDOF model for ``sdof``), bounded empirically by the
    spread between the method's amplitude and the vertex of a least-squares parabola through
    the unsmoothed per-revolution amplitudes around the peak. ``peak`` is not corrected
    (the paper's definition): its interval is widened, and the crossing's note says so when
    this term dominates.
``b_zero`` (d)
    Data preparation / zeroing: what the zeroing reference held, ``A ZEROING_SHARE max(zc,
    contamination)``: a share (:data:`ZEROING_SHARE`, 1/8) of the zeroing correction added
    back (``zeroing_correction_pct``; the growth law it assumes is uncertain) or of the
    reference window's estimated contamination (``contamination_pct``; the baseline removal
    takes most of it).

Frequency (c): the truth's resonant frequency is ``EO Omega / 2 pi`` of one revolution, and
every revolution whose amplitude lies within ``h_A`` of the estimate may be it. The interval
spans the frequencies of that plateau of revolutions (contiguous around the peak) widened by
half a revolution's frequency step on each side, and at least ``f +- 1.96 freq_std_hz``.

Phase: ``psi +- (1.96 sqrt(s_noise^2 + s_layout^2) / A + max |psi_k - psi|)`` over the same
plateau revolutions ``k`` (the phase turns by pi through a resonance, so which revolution is
the peak matters).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .fit import design_matrix

__all__ = ["Z95", "MODEL_ERROR", "ZEROING_SHARE", "CN_NOTE_THRESHOLD", "TERM_NOTE_PCT", "IntervalTerms",
           "crossing_intervals", "dwell_intervals", "layout_gain", "crossing_notes"]

#: Share of the zeroing reference's response (the correction added back, or the window's
#: estimated contamination) left as an error after the correction / baseline removal: a bound
#: calibrated with ``bench/bench_intervals.py`` (errors of 0.2-0.4 % after 9 % corrections).
ZEROING_SHARE = 0.125
#: Two-sided 95 % normal quantile.
Z95 = 1.959963984540054
#: Unmodelled per-probe content relative to the response's amplitude (the layout term).
MODEL_ERROR = 2e-3
#: A crossing whose layout has a condition number of B (Eq. 16) above this gets a note: its
#: amplitude error is dominated by the layout (e.g. probes at 5, 51, 97 deg at EO 8: CN 433).
CN_NOTE_THRESHOLD = 50.0
#: A term whose blade-median share of the amplitude exceeds this (percent) is named in a note.
TERM_NOTE_PCT = 1.0


@dataclass(frozen=True, slots=True, eq=False)
class IntervalTerms:
    """The terms of one crossing's amplitude interval, per blade (pk-pk, m).

    Attributes
    ----------
    noise_m, layout_m : ndarray, shape (n_blades,)
        Standard errors (a).
    model_m, zeroing_m : ndarray, shape (n_blades,)
        Bias bounds (b, e) and (d).
    half_width_m : ndarray, shape (n_blades,)
        ``1.96 sqrt(noise^2 + layout^2) + model + zeroing``.
    """

    noise_m: np.ndarray
    layout_m: np.ndarray
    model_m: np.ndarray
    zeroing_m: np.ndarray
    half_width_m: np.ndarray


def layout_gain(probe_angles_rad, engine_orders, index: int, phasor: np.ndarray) -> np.ndarray:
    """``sqrt(u^T (B^T B)^-1 u)`` per blade: the amplitude's noise gain of the layout.

    Parameters
    ----------
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : tuple of int
        Fitted jointly.
    index : int
        This crossing's order among them.
    phasor : ndarray of complex, shape (n_blades,)
        The response ``a1 + i a2`` at the peak (its direction ``u``).

    Returns
    -------
    ndarray, shape (n_blades,)
        ``inf`` when the probes cannot separate the unknowns.
    """
    B = design_matrix(probe_angles_rad, engine_orders)
    try:
        G = np.linalg.inv(B.T @ B)
    except np.linalg.LinAlgError:
        return np.full(np.shape(phasor), np.inf)
    i = 1 + 2 * int(index)
    P = np.asarray(phasor, dtype=complex)
    with np.errstate(all="ignore"):
        u1, u2 = np.cos(np.angle(P)), np.sin(np.angle(P))
        g = u1 * u1 * G[i, i] + 2 * u1 * u2 * G[i, i + 1] + u2 * u2 * G[i + 1, i + 1]
    return np.sqrt(np.maximum(g, 0.0))


def _noise(amp_raw: np.ndarray) -> np.ndarray:
    from .methods import amplitude_noise

    return amplitude_noise(amp_raw)


def _parabola_peak(amp: np.ndarray, rev: np.ndarray, half: int) -> np.ndarray:
    """Vertex of a least-squares parabola through ``rev +- half`` of each blade's sequence."""
    from .resonance import _parabolic

    n, nb = amp.shape
    ok = np.isfinite(rev)
    r = np.clip(np.where(ok, rev, 0).round().astype(np.int64), 0, n - 1)
    _, val = _parabolic(amp, r, half)
    return np.where(ok, val, np.nan)


def crossing_intervals(peaks, amp_seq_m: np.ndarray, phase_seq_rad: np.ndarray, amp_raw_m: np.ndarray,
                       freq_hz: np.ndarray, lo: int, hi: int, *, gain: np.ndarray, half_power_width: int,
                       zeroing_correction: float = math.nan, contamination: float = math.nan,
                       cff_window: int | None = None):
    """The 95 % intervals of one crossing's peaks (see the module docstring).

    Parameters
    ----------
    peaks : ResonancePeaks
        The method's estimate; ``revolution`` indexes the sequences below.
    amp_seq_m, phase_seq_rad : ndarray, shape (n_rev, n_blades)
        Per-revolution amplitude (pk-pk, m) and phase the crossing was picked from (zeroing
        correction included).
    amp_raw_m : ndarray, shape (n_rev, n_blades)
        Unsmoothed per-revolution amplitudes (the noise and the parabola).
    freq_hz : ndarray, shape (n_rev,)
        ``EO Omega / 2 pi`` per revolution.
    lo, hi : int
        The crossing's window.
    gain : ndarray, shape (n_blades,)
        :func:`layout_gain`.
    half_power_width : int
        Revolutions; sets the parabola's half-width (a sixth of it, at least 2).
    zeroing_correction, contamination : float
        Fractions of the peak (NaN: none).
    cff_window : int, optional
        The CFF's revolutions per fit (its noise term, see the module docstring).

    Returns
    -------
    peaks : ResonancePeaks
        With ``amp_ci95_m``, ``freq_ci95_hz``, ``phase_ci95_rad`` set.
    terms : IntervalTerms
    """
    from dataclasses import replace

    A = np.asarray(peaks.amp_pkpk_m, dtype=float)
    nb = A.size
    n = np.asarray(freq_hz).size
    rev = np.asarray(peaks.revolution, dtype=float)
    raw = np.asarray(amp_raw_m, dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        s_raw = _noise(raw[lo:hi + 1])
        std = np.asarray(peaks.amp_std_m if peaks.amp_std_m is not None else np.full(nb, np.nan), dtype=float)
        if cff_window is not None:
            std = s_raw / math.sqrt(max(int(cff_window), 1))
        s_noise = np.where(np.isfinite(std), std, s_raw)
        s_noise = np.where(np.isfinite(s_noise), s_noise, 0.0)
        s_layout = np.where(np.isfinite(gain), gain, 0.0) * MODEL_ERROR * A
        half = max(2, int(half_power_width) // 6)
        par = _parabola_peak(raw, rev, half)
        model = np.abs(A - par)
        model = np.where(np.isfinite(model), model, 0.0)
        zc = zeroing_correction if math.isfinite(zeroing_correction) else 0.0
        ct = contamination if math.isfinite(contamination) else 0.0
        zero = A * ZEROING_SHARE * max(zc, ct)
    rand = Z95 * np.sqrt(s_noise ** 2 + s_layout ** 2)
    h = rand + model + zero
    terms = IntervalTerms(noise_m=s_noise, layout_m=s_layout, model_m=model, zeroing_m=zero, half_width_m=h)
    f = np.asarray(freq_hz, dtype=float)
    step = np.abs(np.gradient(f)) if n > 1 else np.zeros(n)
    amp = np.asarray(amp_seq_m, dtype=float)
    ph = np.asarray(phase_seq_rad, dtype=float)
    fci = np.full((nb, 2), np.nan)
    pci = np.full((nb, 2), np.nan)
    fstd = np.asarray(peaks.freq_std_hz if peaks.freq_std_hz is not None else np.zeros(nb), dtype=float)
    psi = np.asarray(peaks.phase_rad if peaks.phase_rad is not None else np.full(nb, np.nan), dtype=float)
    for b in range(nb):
        if not (np.isfinite(A[b]) and np.isfinite(rev[b])):
            continue
        k = int(np.clip(round(rev[b]), lo, hi))
        floor = A[b] - h[b]
        a0 = k
        while a0 > lo and np.isfinite(amp[a0 - 1, b]) and amp[a0 - 1, b] >= floor:
            a0 -= 1
        a1 = k
        while a1 < hi and np.isfinite(amp[a1 + 1, b]) and amp[a1 + 1, b] >= floor:
            a1 += 1
        fs = f[a0:a1 + 1]
        st = 0.5 * float(np.max(step[a0:a1 + 1]))
        fb = float(peaks.freq_hz[b])
        fz = Z95 * (float(fstd[b]) if np.isfinite(fstd[b]) else 0.0)
        fci[b] = (min(float(np.min(fs)) - st, fb - fz), max(float(np.max(fs)) + st, fb + fz))
        if np.isfinite(psi[b]):
            dphi = np.angle(np.exp(1j * (ph[a0:a1 + 1, b] - psi[b])))
            dphi = dphi[np.isfinite(dphi)]
            hp = rand[b] / A[b] + (float(np.max(np.abs(dphi))) if dphi.size else 0.0)
            hp = min(hp, math.pi)
            pci[b] = (psi[b] - hp, psi[b] + hp)
    aci = np.stack([A - h, A + h], axis=1)
    return replace(peaks, amp_ci95_m=aci, freq_ci95_hz=fci, phase_ci95_rad=pci), terms


def dwell_intervals(peaks):
    """A dwell's intervals: ``+- 1.96`` its standard uncertainties (the mean of many
    revolutions of a steady response), the phase's from the amplitude's."""
    from dataclasses import replace

    A = np.asarray(peaks.amp_pkpk_m, dtype=float)
    s = np.asarray(peaks.amp_std_m, dtype=float)
    fs = np.asarray(peaks.freq_std_hz, dtype=float)
    f = np.asarray(peaks.freq_hz, dtype=float)
    with np.errstate(all="ignore"):
        hp = np.minimum(Z95 * s / A, math.pi)
    psi = np.asarray(peaks.phase_rad, dtype=float)
    return replace(peaks, amp_ci95_m=np.stack([A - Z95 * s, A + Z95 * s], 1),
                   freq_ci95_hz=np.stack([f - Z95 * fs, f + Z95 * fs], 1),
                   phase_ci95_rad=np.stack([psi - hp, psi + hp], 1))


def _median_pct(x: np.ndarray, A: np.ndarray) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        v = np.nanmedian(100.0 * np.asarray(x) / np.asarray(A))
    return float(v) if np.isfinite(v) else 0.0


def crossing_notes(*, eo: int, method: str, cn: float, terms: IntervalTerms, amp_pkpk_m: np.ndarray,
                   contamination: float, contamination_limit: float, zeroing_correction: float,
                   nsv_overlap: list, other_crossings: list) -> tuple:
    """Notes naming what spoils one crossing's estimate (and so widens its interval).

    Parameters
    ----------
    nsv_overlap : list of str
        Descriptions of detected non-synchronous vibrations overlapping the crossing.
    other_crossings : list of int
        Engine orders of other crossings overlapping this one's revolutions.
    """
    A = np.asarray(amp_pkpk_m, dtype=float)
    notes = []
    if math.isfinite(cn) and cn > CN_NOTE_THRESHOLD:
        notes.append(f"poor layout: CN {cn:.3g} > {CN_NOTE_THRESHOLD:g} at EO {eo}: the probes barely separate "
                     f"the response, its amplitude is uncertain by about "
                     f"{1.96 * _median_pct(terms.layout_m, A):.2g} % (layout term)")
    model = _median_pct(terms.model_m, A)
    if model > TERM_NOTE_PCT:
        what = ("fast sweep or a peak sharp for the smoothing: the peak pick is not corrected, its interval is "
                "widened" if method.startswith("peak") else "the method's model departs from the data: the "
                "interval is widened")
        notes.append(f"{what} by the spread to a parabola through the unsmoothed amplitudes, {model:.2g} % "
                     f"(blade median)")
    ct = 100.0 * contamination if math.isfinite(contamination) else 0.0
    zc = 100.0 * zeroing_correction if math.isfinite(zeroing_correction) else 0.0
    if contamination > contamination_limit or zc > 2 * TERM_NOTE_PCT:
        notes.append(f"short window / no quiet reference: the zeroing reference held about {max(ct, zc):.2g} % of "
                     f"the peak; the interval includes {_median_pct(terms.zeroing_m, A):.2g} % for it")
    for s in nsv_overlap:
        notes.append(f"contaminated: a non-synchronous vibration overlaps this crossing's revolutions ({s}); the "
                     f"EO {eo} amplitudes include part of it")
    if other_crossings:
        notes.append(f"a crossing of EO {', '.join(map(str, sorted(set(other_crossings))))} overlaps this one's "
                     f"revolutions: the responses add up in these amplitudes")
    return tuple(notes)
