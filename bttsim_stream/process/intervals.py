"""95 % intervals of each blade's resonant amplitude, frequency and phase, and the notes that
say what limits them.

Every crossing's per-blade estimate (:mod:`.methods`) gets ``amp_ci95_m``, ``freq_ci95_hz``
and ``phase_ci95_rad`` (``[lo, hi]``). The interval is built from the data only (the truth is
never used: it only validates, ``bench/bench_intervals.py``). Amplitudes are peak-to-peak, m.

Amplitude half-width (conservative sum of the bias bounds on top of the root-sum-square of
the random terms)::

    h_A = 1.96 sqrt(s_noise^2 + s_layout^2) + D_model + D_sampling + D_orders + b_zero

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
    ``peak``; the window for ``cff``; the SDOF model for ``sdof``), bounded by the spread
    between the method's amplitude and a second estimate: the vertex of a least-squares
    parabola through the unsmoothed per-revolution amplitudes around the peak (zeroing
    correction included; its own flattening, which goes as the half-width^4, extrapolated
    from two half-widths), and the swept SDOF fit's peak (:func:`~.methods.sdof_method`: the
    sweep is in its model, the zeroing in its constant). The largest spread counts. ``peak``
    is not corrected (the paper's definition): its interval is widened, and the crossing's
    note says so.
``D_sampling`` (c, e)
    Revolution quantisation of the amplitude: ``2 |P''| (1/8 + v/2)`` (:func:`_sampling`),
    ``P''`` the curvature of the complex response at the peak, ``v`` the variance of the
    probes' arrival times in a revolution (plus the CFF window's).
``D_orders`` (another EO)
    Several engine orders fitted jointly: the spread between the joint and a single-order
    amplitude at the peak (``orders_m``).
``b_zero`` (d)
    Data preparation / zeroing, on every crossing (a quiet reference too: the prepared
    baseline can leave a constant of about a percent of the peak): the swept SDOF fit's
    constant ``c`` measures what the zeroing (and its correction) left in the responses, a
    complex error ``e`` per blade. The sequences with ``e`` taken out give a second peak; the
    interval spans both peaks (so it is asymmetric), and the frequency and phase intervals
    both plateaus; plus, when the reference window was not quiet (or the sweep fast), the
    fit's misfit beyond the noise. Where the SDOF fit fails:
    ``max(2 |correction|, contamination A)``.

Frequency (c): the truth's resonant frequency is ``EO Omega / 2 pi`` of one revolution. With
the amplitude sequence within ``h_A`` of the truth's everywhere, the truth's peak revolution
has an amplitude within ``2 h_A`` of the estimate: the interval spans the frequencies of that
plateau of revolutions (contiguous around the peak) widened by half a revolution's frequency
step on each side, and at least ``f +- 1.96 freq_std_hz``.

Phase: ``psi +- (asin(h_A / A) + max |psi_k - psi|)`` over the same plateau revolutions ``k``
(an error of ``h_A`` in the complex response turns it by at most ``asin(h_A / A)``; the phase
turns by pi through a resonance, so which revolution is the peak matters).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .fit import design_matrix
from .spans import as_rows

__all__ = ["Z95", "MODEL_ERROR", "CN_NOTE_THRESHOLD", "TERM_NOTE_PCT", "IntervalTerms",
           "crossing_intervals", "dwell_intervals", "dwell_misfit", "layout_gain", "crossing_notes", "no_crossing_note",
           "blade_medians"]

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
    orders_m : ndarray, shape (n_blades,), or None
        The part of ``model_m`` due to the other engine orders fitted jointly.
    """

    noise_m: np.ndarray
    layout_m: np.ndarray
    model_m: np.ndarray
    zeroing_m: np.ndarray
    half_width_m: np.ndarray
    orders_m: np.ndarray | None = None


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
    from .resonance import parabolic_peak

    n, nb = amp.shape
    ok = np.isfinite(rev)
    r = np.clip(np.where(ok, rev, 0).round().astype(np.int64), 0, n - 1)
    _, val = parabolic_peak(amp, r, half)
    return np.where(ok, val, np.nan)


def crossing_intervals(peaks, amp_seq_m: np.ndarray, phase_seq_rad: np.ndarray, amp_raw_m: np.ndarray,
                       freq_hz: np.ndarray, lo: int, hi: int, *, gain: np.ndarray, half_power_width: int,
                       zeroing_m: np.ndarray | None = None, zeroing_error: np.ndarray | None = None,
                       second_m: np.ndarray | None = None, orders_m: np.ndarray | None = None,
                       probe_spread: float = 0.0,
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
    zeroing_m : ndarray, shape (n_blades,), optional
        A bound on the zeroing error (pk-pk, m) where ``zeroing_error`` is not known.
    zeroing_error : ndarray of complex, shape (n_blades,), optional
        What the zeroing left in the responses ``a1 + i a2`` (m; NaN: unknown).
    second_m : ndarray, shape (n_blades,), optional
        A second, independent estimate of the amplitude (pk-pk, m): the spread to it bounds
        the method's bias.
    probe_spread : float
        Variance of the probes' arrival times within a revolution, revolutions^2.
    orders_m : ndarray, shape (n_blades,), optional
        Several engine orders fitted jointly: the spread between the joint and the
        single-order amplitude (pk-pk, m), added to the model term.
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
    raw = as_rows(amp_raw_m)
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
        par2 = _parabola_peak(raw, rev, max(2, half // 2))
        # the vertex's own flattening goes as half^4: extrapolated from the two half-widths
        model = np.maximum(np.abs(A - par), np.abs(A - (par2 + (par2 - par) / 15.0)))
        model = np.where(np.isfinite(model), model, 0.0)
        zero = np.zeros(nb) if zeroing_m is None else np.asarray(zeroing_m, dtype=float)
        zero = np.where(np.isfinite(zero), zero, 0.0)
    amp = as_rows(amp_seq_m)
    ph = as_rows(phase_seq_rad)
    alt = _without_error(amp, ph, lo, hi, zeroing_error)
    shift = np.zeros(nb) if alt is None else alt[2]
    if second_m is not None:  # an independent estimate (the swept SDOF fit): the spread to it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            d2 = np.abs(A + shift - np.asarray(second_m, dtype=float))
        model = np.maximum(model, np.where(np.isfinite(d2), d2, 0.0))
    w = 1 if cff_window is None else max(int(cff_window), 1)  # the CFF averages w revolutions too
    model = model + _sampling(amp, ph, rev, lo, hi, probe_spread + (w * w - 1) / 12.0, half)
    if orders_m is not None:  # the other engine orders fitted jointly: a bias bound of its own
        model = model + np.where(np.isfinite(orders_m), np.asarray(orders_m, dtype=float), 0.0)
    rand = Z95 * np.sqrt(s_noise ** 2 + s_layout ** 2)
    h = rand + model + zero
    terms = IntervalTerms(noise_m=s_noise, layout_m=s_layout, model_m=model, zeroing_m=zero + np.abs(shift),
                          half_width_m=h + np.abs(shift), orders_m=orders_m)
    f = np.asarray(freq_hz, dtype=float)
    step = np.abs(np.gradient(f)) if n > 1 else np.zeros(n)
    fci = np.full((nb, 2), np.nan)
    pci = np.full((nb, 2), np.nan)
    fstd = np.asarray(peaks.freq_std_hz if peaks.freq_std_hz is not None else np.zeros(nb), dtype=float)
    psi = np.asarray(peaks.phase_rad if peaks.phase_rad is not None else np.full(nb, np.nan), dtype=float)
    for b in range(nb):
        if not (np.isfinite(A[b]) and np.isfinite(rev[b])):
            continue
        k = int(np.clip(round(rev[b]), lo, hi))
        a0, a1 = _plateau(amp[:, b], k, A[b] - 2.0 * h[b], lo, hi)
        dphi = ph[a0:a1 + 1, b] - psi[b]
        if alt is not None and np.isfinite(alt[3][b]):  # the sequence without the zeroing error
            k2 = int(alt[3][b]) - lo  # alt's rows are revolutions lo .. hi
            c0, c1 = _plateau(alt[0][:, b], k2, float(alt[0][k2, b]) - 2.0 * h[b], 0, hi - lo)
            dphi = np.concatenate([dphi, alt[1][c0:c1 + 1, b] - ph[k, b] + np.angle(np.exp(1j * (ph[k, b] - psi[b])))])
            a0, a1 = min(a0, lo + c0), max(a1, lo + c1)
        fs = f[a0:a1 + 1]
        st = 0.5 * float(np.max(step[a0:a1 + 1]))
        fb = float(peaks.freq_hz[b])
        fz = Z95 * (float(fstd[b]) if np.isfinite(fstd[b]) else 0.0)
        fci[b] = (min(float(np.min(fs)) - st, fb - fz), max(float(np.max(fs)) + st, fb + fz))
        if np.isfinite(psi[b]):
            dphi = np.angle(np.exp(1j * dphi))
            dphi = dphi[np.isfinite(dphi)]
            hp = math.asin(min(h[b] / A[b], 1.0)) + (float(np.max(np.abs(dphi))) if dphi.size else 0.0)
            hp = min(hp, math.pi)
            pci[b] = (psi[b] - hp, psi[b] + hp)
    aci = np.stack([A + np.minimum(shift, 0.0) - h, A + np.maximum(shift, 0.0) + h], axis=1)
    return replace(peaks, amp_ci95_m=aci, freq_ci95_hz=fci, phase_ci95_rad=pci), terms


def _sampling(amp: np.ndarray, ph: np.ndarray, rev: np.ndarray, lo: int, hi: int, spread: float,
              step: int = 1) -> np.ndarray:
    """The revolution sampling's bias bound per blade (pk-pk, m): ``2 |P''| (1/8 + spread / 2)``.

    ``P''`` is the curvature of the complex response at the peak (per revolution^2): its second
    difference over ``step`` revolutions each side, divided by ``step^2`` (the parabola's
    half-width: the noise's share falls as ``step^-2``).
    The continuous peak lies within half a revolution of a sampled one (``|P''| / 8``), and one
    revolution's fit averages the response over the probes' arrival times, of variance
    ``spread`` (revolutions^2; ``|P''| spread / 2``; the CFF's ``w`` revolutions add
    ``(w^2 - 1) / 12``). Negligible for a slow sweep (``P''``
    goes as the inverse square of the half-power width in revolutions).
    """
    n, nb = amp.shape
    s = max(1, min(int(step), (n - 1) // 2))
    if n < 3:
        return np.zeros(nb)
    ok = np.isfinite(rev)
    k = np.clip(np.where(ok, rev, lo).round().astype(np.int64), s, n - 1 - s)
    cols = np.arange(nb)

    def P(r):  # the responses at revolutions r (one per blade), not the whole run's
        return 0.5 * amp[r, cols] * np.exp(1j * ph[r, cols])

    d2 = np.abs(P(k + s) - 2.0 * P(k) + P(k - s)) / (s * s)
    out = 2.0 * d2 * (0.125 + 0.5 * float(spread))
    return np.where(ok & np.isfinite(out), out, 0.0)


def _plateau(a: np.ndarray, k: int, floor: float, lo: int, hi: int) -> tuple[int, int]:
    """The revolutions contiguous with ``k`` (within ``lo .. hi``) whose amplitude is at least
    ``floor``."""
    a0 = k
    while a0 > lo and np.isfinite(a[a0 - 1]) and a[a0 - 1] >= floor:
        a0 -= 1
    a1 = k
    while a1 < hi and np.isfinite(a[a1 + 1]) and a[a1 + 1] >= floor:
        a1 += 1
    return a0, a1


def _without_error(amp: np.ndarray, ph: np.ndarray, lo: int, hi: int, error):
    """The crossing's sequences with a complex error ``error`` (per blade, ``a1 + i a2``, m)
    taken out: ``(amp, phase, peak shift, peak revolution)`` (None without an error; NaN
    revolution for a blade without). The amplitude and phase are those of revolutions
    ``lo .. hi`` only (row 0 is revolution ``lo``); the peak revolution is the run's index
    (not counted from ``lo``)."""
    if error is None:
        return None
    e = np.asarray(error, dtype=complex)
    P2 = 0.5 * amp[lo:hi + 1] * np.exp(1j * ph[lo:hi + 1]) - np.where(np.isfinite(e), e, 0.0)[None, :]
    a2 = 2.0 * np.abs(P2)
    w1 = np.where(np.isfinite(amp[lo:hi + 1]), amp[lo:hi + 1], -np.inf)
    w2 = np.where(np.isfinite(a2), a2, -np.inf)
    k2 = lo + np.argmax(w2, axis=0)
    ok = np.isfinite(e) & np.isfinite(w2).any(axis=0)
    shift = np.where(ok, np.max(w2, axis=0) - np.max(w1, axis=0), 0.0)
    return a2, np.angle(P2), np.where(np.isfinite(shift), shift, 0.0), np.where(ok, k2, np.nan)


def dwell_misfit(d_mean_m: np.ndarray, probe_angles_rad, engine_orders, index: int,
                 tip_radius_m: float | None = None) -> tuple[np.ndarray, int]:
    """A dwell's systematic misfit: what the probes' positions put into each blade's response
    that no mean over revolutions takes out.

    A steady response is the same every revolution, so a probe angle error (or any constant
    per probe) is too: the revolutions' mean cannot reduce it, and a dwell alone cannot be
    calibrated (its response is a constant like the error). What the fit of Eq. 16 cannot
    absorb shows in its residual; the part common to every blade is the probes' (a blade's
    own misfit, such as the sampling-angle harmonics, changes with its phase and averages out
    over a travelling wave). Its variance ``s^2 = |r_c|^2 / (n_probes - p)`` through the
    layout, ``2 sqrt(s^2 u^T (B^T B)^-1 u)``, is the amplitude's standard uncertainty (pk-pk):
    the unseen part of the error, inside the model's span, is taken as large per degree of
    freedom as the seen part.

    Parameters
    ----------
    d_mean_m : ndarray, shape (n_blades, n_probes)
        Each blade's mean displacement at each probe over the dwell, m (NaN: no sample).
    probe_angles_rad : array_like, shape (n_probes,)
    engine_orders : tuple of int
        Fitted jointly.
    index : int
        The dwell's order among them.
    tip_radius_m : float, optional
        Fit at the sampling angles ``theta_j - d_j / R`` (as the report's fits).

    Returns
    -------
    std_m : ndarray, shape (n_blades,)
        Pk-pk standard uncertainty (NaN where a blade has too few probes; 0 with no blade).
    dof : int
        Degrees of freedom of ``s^2`` (probes with data less the fit's unknowns; 0: the misfit
        cannot be seen).
    """
    d = np.asarray(d_mean_m, dtype=float)
    th = np.atleast_1d(np.asarray(probe_angles_rad, dtype=float))
    nb, npr = d.shape
    p = 1 + 2 * len(engine_orders)
    res = np.full((nb, npr), np.nan)
    gain = np.full(nb, np.nan)
    i = 1 + 2 * int(index)
    for b in range(nb):  # one fit per blade (its own sampling angles)
        ok = np.isfinite(d[b])
        if ok.sum() <= p:
            continue
        B = design_matrix(th[ok] - (d[b, ok] / tip_radius_m if tip_radius_m else 0.0), engine_orders)
        coef, *_ = np.linalg.lstsq(B, d[b, ok], rcond=None)
        res[b, ok] = d[b, ok] - B @ coef
        G = np.linalg.pinv(B.T @ B)
        u1, u2 = np.cos(math.atan2(coef[i + 1], coef[i])), np.sin(math.atan2(coef[i + 1], coef[i]))
        gain[b] = max(u1 * u1 * G[i, i] + 2 * u1 * u2 * G[i, i + 1] + u2 * u2 * G[i + 1, i + 1], 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        common = np.nanmean(res, axis=0)
    seen = np.isfinite(common)
    dof = int(seen.sum()) - p
    if dof <= 0:
        return np.full(nb, np.nan), 0
    s2 = float(np.sum(common[seen] ** 2)) / dof
    return 2.0 * np.sqrt(s2 * gain), dof


def dwell_intervals(peaks, layout_m=None, probes_m=None, dof: int = 0, zeroing_m=0.0):
    """A dwell's intervals: ``1.96 sqrt(s_noise^2 + s_layout^2) + t_dof s_probes + b_zero``
    for the amplitude (the noise: the mean of many revolutions of a steady response; the
    layout term as a crossing's; the probes' systematic misfit, :func:`dwell_misfit`, with
    Student's 95 % quantile for its ``dof`` degrees of freedom; ``zeroing_m`` the zeroing
    reference's bias bound, NaN: unknown, and so no interval), not below zero; the phase
    turned by at most ``asin(h / A)``; the frequency ``+- 1.96`` its standard uncertainty."""
    from dataclasses import replace

    from scipy.special import stdtrit  # = scipy.stats.t.ppf, without importing scipy.stats (0.3 s, 36 MB)

    A = np.asarray(peaks.amp_pkpk_m, dtype=float)
    s = np.asarray(peaks.amp_std_m, dtype=float)
    lay = np.zeros_like(A) if layout_m is None else np.asarray(layout_m, dtype=float)
    sys_ = np.zeros_like(A) if probes_m is None or dof <= 0 else np.asarray(probes_m, dtype=float)
    t95 = float(stdtrit(dof, 0.975)) if dof > 0 else 0.0
    h = Z95 * np.sqrt(s * s + lay * lay) + t95 * sys_ + zeroing_m  # a blade whose misfit is unseen: no interval
    fs = np.asarray(peaks.freq_std_hz, dtype=float)
    f = np.asarray(peaks.freq_hz, dtype=float)
    with np.errstate(all="ignore"):
        hp = np.where(h < A, np.arcsin(np.minimum(h / A, 1.0)), np.where(np.isnan(h), np.nan, math.pi))
    psi = np.asarray(peaks.phase_rad, dtype=float)
    return replace(peaks, amp_ci95_m=np.stack([np.maximum(A - h, 0.0), A + h], 1),
                   freq_ci95_hz=np.stack([f - Z95 * fs, f + Z95 * fs], 1),
                   phase_ci95_rad=np.stack([psi - hp, psi + hp], 1))


def _median_pct(x: np.ndarray, A: np.ndarray) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        v = np.nanmedian(100.0 * np.asarray(x) / np.asarray(A))
    return float(v) if np.isfinite(v) else 0.0


def crossing_notes(*, eo: int, method: str, cn: float, terms: IntervalTerms, amp_pkpk_m: np.ndarray,
                   contamination: float, contamination_limit: float, zeroing_correction: float,
                   nsv_overlap: list, other_crossings: list, half_power_width: float = math.inf,
                   fast_sweep_revolutions: float = 0.0) -> tuple:
    """Notes naming what spoils one crossing's estimate (and so widens its interval); each is
    computed from the data only.

    Parameters
    ----------
    half_power_width : float
        Revolutions over which the sweep crosses the half-power band.
    fast_sweep_revolutions : float
        Below this, the sweep is named as fast.
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
    if half_power_width < fast_sweep_revolutions:
        what = {"peak": "the per-revolution fits and the smoothing flatten the peak, not corrected: the interval is "
                        "widened by the spread to the swept SDOF fit and the revolution sampling",
                "cff": "the CFF window and the per-revolution fits flatten the peak, not corrected: the interval is "
                       "widened by the spread to the swept SDOF fit and the revolution sampling",
                "sdof": "the SDOF model carries the sweep; the interval holds its misfit and the revolution "
                        "sampling"}.get(method, "the interval is widened for the sweep")
        notes.append(f"fast sweep: the half-power band is crossed in {half_power_width:.0f} revolutions (< "
                     f"{fast_sweep_revolutions:g}): {what}, {model:.2g} % (blade median)")
    elif model > TERM_NOTE_PCT:
        what = ("a peak sharp for the smoothing: the peak pick is not corrected, its interval is "
                "widened" if method.startswith("peak") else "the method's model departs from the data: the "
                "interval is widened")
        notes.append(f"{what} by the spread to a second estimate of the peak, {model:.2g} % (blade median)")
    ct = 100.0 * contamination if math.isfinite(contamination) else 0.0
    zc = 100.0 * zeroing_correction if math.isfinite(zeroing_correction) else 0.0
    if contamination > contamination_limit or zc > 2 * TERM_NOTE_PCT:
        notes.append(f"short window / no quiet reference: the zeroing reference held about {max(ct, zc):.2g} % of "
                     f"the peak; the interval includes {_median_pct(terms.zeroing_m, A):.2g} % for it")
    for s in nsv_overlap:
        notes.append(f"contaminated: a non-synchronous vibration overlaps this crossing's revolutions ({s}); the "
                     f"EO {eo} amplitudes include part of it")
    if terms.orders_m is not None and _median_pct(terms.orders_m, A) > TERM_NOTE_PCT:
        notes.append(f"other engine orders fitted jointly with EO {eo}: the joint and the single-order amplitudes "
                     f"differ by {_median_pct(terms.orders_m, A):.2g} % (blade median), added to the interval")
    if other_crossings:
        notes.append(f"a crossing of EO {', '.join(map(str, sorted(set(other_crossings))))} overlaps this one's "
                     f"revolutions: the responses add up in these amplitudes")
    return tuple(notes)


def blade_medians(amp_pkpk_m: np.ndarray) -> np.ndarray:
    """Each revolution's blade-median amplitude per order, shape (n_rev, n_eo), of amplitudes
    (n_rev, n_blades, n_eo) (NaN where a revolution has none): each revolution's own (the same
    numbers for a block of revolutions as for the whole run)."""
    a = np.asarray(amp_pkpk_m, dtype=float)
    out = np.empty((a.shape[0], a.shape[2]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i in range(a.shape[2]):
            out[:, i] = np.nanmedian(a[:, :, i], axis=1)
    return out


def no_crossing_note(amp_pkpk_m: np.ndarray | None, omega_rad_s: np.ndarray, engine_orders, ratio: float,
                     medians: np.ndarray | None = None) -> str | None:
    """A note for a run where no crossing was found but the response changes a lot: the run may
    lie inside a resonance (no quiet reference, a resonance broader than the run, a peak at
    its end), so its amplitudes are not a resonance's, and neither is any zeroing quiet.

    Parameters
    ----------
    amp_pkpk_m : ndarray, shape (n_rev, n_blades, n_eo), or None
        Per-revolution amplitudes of the fitted orders (the prepared fits); None: ``medians``.
    omega_rad_s : ndarray, shape (n_rev,)
    engine_orders : tuple of int
    ratio : float
        The detection's prominence ratio: a blade-median amplitude whose 95th percentile over
        the run is at least ``ratio`` times its 5th is named.
    medians : ndarray, shape (n_rev, n_eo), optional
        :func:`blade_medians` of the amplitudes, when computed by blocks of revolutions.

    Returns
    -------
    str or None
    """
    meds = blade_medians(amp_pkpk_m) if medians is None else medians
    parts = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i, eo in enumerate(engine_orders):
            med = meds[:, i]
            ok = np.isfinite(med)
            if ok.sum() < 8:
                continue
            lo, hi = np.percentile(med[ok], [5.0, 95.0])
            if lo > 0 and hi >= ratio * lo:
                k = int(np.flatnonzero(ok)[np.argmax(med[ok])])
                parts.append(f"EO {eo} {1e3 * lo:.3g}-{1e3 * hi:.3g} mm ({hi / lo:.1f} x), largest at "
                             f"{float(omega_rad_s[k]) * 60.0 / (2.0 * math.pi):.0f} rpm")
    if not parts:
        return None
    return ("the response changes strongly over the run though no crossing was found (blade-median amplitude, "
            "5th-95th percentile: " + "; ".join(parts) + "): the run may lie inside a resonance (too short for a "
            "quiet reference, or a resonance broader than the run); no resonance amplitude is reported and the "
            "zeroing reference is not quiet")
