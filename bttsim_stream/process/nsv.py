"""Non-synchronous vibration (NSV): detection, order alias, nodal diameter and amplitude.

Flutter and rotating stall make the blades vibrate at a rotor-frame frequency ``f`` that is
not a whole multiple of the shaft frequency, as a travelling wave of nodal diameter ``k``:

``x_b(t) = A sin(2 pi f t + 2 pi k b / N_b + c)``  (same sign convention as
:mod:`.travelling_wave`: ``+k`` forward).

Sampling
--------
Within a block of ``L`` revolutions at nearly constant speed the blade reaches probe ``j``
in revolution ``n`` at rotor angle ``2 pi n + psi_bj`` (``psi_bj`` the arrival angle,
``theta_j - theta_b - theta_OPR`` mod 2 pi, :mod:`.displacement`), so the Eq. 1 samples are

``d_nbj = A sin(nu (2 pi n + psi_bj) + 2 pi k b / N_b + c)``,  ``nu = f / f_shaft``

(the *order*, ``2 pi f / Omega``, not an integer). What this sampling can observe:

* each blade and probe gives one sample per revolution: the sequence in ``n`` shows only
  the **alias** ``mu = |nu - round(nu)|`` in ``[0, 0.5]`` cycles per revolution (a real
  sinusoid cannot tell ``nu`` from ``-nu``). A synchronous (engine-order) response has
  ``mu = 0``: that is what tells NSV from forced response;
* the probes at different angles see the phase pattern ``exp(i nu psi_bj)``, which fixes
  the whole part of ``nu`` among the candidates ``m +- mu`` -- as far as the probe layout
  can: two candidates whose patterns the probes cannot tell apart (e.g. ``nu`` and
  ``nu + P`` for ``P`` equally spaced probes) are both listed (``order_alternatives``);
* with the order chosen, the blades' phases after removing ``nu psi_bj`` give the signed
  ND ``k`` by a spatial DFT (a wrong whole part ``m`` of the order shifts the ND by the same
  amount: the stationary-frame order ``nu - k`` is what one probe alone sees).

Method (per block, vectorised over the blocks of a chunk)
---------------------------------------------------------
Each blade and probe's block of displacements has its mean and a quadratic trend in the
revolution removed (the slowly varying synchronous response and the offsets), is Hann
windowed, and transformed along the revolutions (zero-padded FFT). The power summed over
blades and probes, ``S(mu)``, is searched above the synchronous band ``mu >= guard``: the
**detection statistic** is the ratio of its peak to its median over that band (white
noise: about 1.5 with 145 series; an NSV of pk-pk amplitude ``a`` on noise of rms
``sigma`` per sample gives about ``1 + 0.043 L a^2 / sigma^2``, i.e. the threshold 10 is
reached at ``a`` about 2.6 ``sigma`` with ``L = 32``). A block is detected when the
ratio is at least ``ratio_threshold`` (10), the wave's pk-pk amplitude at its ND is at least
``min_amp_m`` (5 um, a noise-free run's numerical floor is far below, the simulator's 8 ns
clock tick is about 3 um of tip motion at 0.19 m and 2500 rpm) and the probe-phase
coherence of the chosen order is at least ``min_coherence``. A **detection** is a run of at
least ``min_blocks`` (2) consecutive detected blocks with the same ND and orders within
``3 / L``: a transient (the free vibration after a fast resonance crossing) does not last.

The alias is refined between FFT bins by a parabola through the log power, the complex
response of each blade and probe is then the windowed DFT at that alias, and the candidate
orders are scored by their **coherence** ``sum_b |sum_j Z_bj exp(-i nu psi_bj)|^2 /
(P sum_bj |Z_bj|^2)`` (1: the probes' phases are exactly those of order ``nu``).

Per revolution, the amplitude of a detection (the growth of a flutter) is the least-squares
fit of ``sin / cos(nu psi_bj)`` to each blade's detrended samples of that revolution.

Conventions: arrays ``(revolution, blade, probe)``, SI units, amplitudes peak-to-peak,
revolutions numbered from 0 (the caller adds its first revolution's number).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["NsvOptions", "NsvScan", "NsvDetection", "NsvTruthRows", "scan_blocks", "screen_block", "detections",
           "detect_nsv",
           "nsv_truth_rows", "score_nsv", "nsv_note", "nsv_table_lines", "is_rigid_body", "rigid_body_note"]

TWO_PI = 2.0 * np.pi
#: The shortest run analysed as one block when it is shorter than ``min_blocks`` blocks.
MIN_WHOLE_RUN = 16
#: ``amp_last_pkpk_m``: the median of the per-revolution amplitudes over this many last revolutions.
LAST_REVOLUTIONS = 8
#: Samples (revolutions x blades x probes) of the whole blocks that :func:`scan_blocks` reads
#: and transforms at once (at least one block): every block is analysed on its own (its
#: spectrum, statistic, peak and fit use its own revolutions only), so chunks of blocks give
#: the same numbers, with temporaries bounded by the chunk (a few arrays of it, 2 MB each)
#: instead of growing with the run.
NSV_CHUNK = 1 << 18


@dataclass(frozen=True, slots=True)
class NsvOptions:
    """Thresholds and block size of the NSV detection (see the module docstring).

    Attributes
    ----------
    block : int
        Revolutions per block (non-overlapping, from revolution 0 of the run), >= 8.
    pad : int
        Zero-padding factor of the FFT along the revolutions.
    guard : float
        Synchronous band: aliases below this (cycles per revolution) are not searched;
        at least 3 bins of the block (the Hann window's main lobe and trend removal).
    ratio_threshold : float
        Peak-to-median power ratio of a detected block.
    min_amp_m : float
        Smallest pk-pk amplitude of the wave at its ND of a detected block, m.
    min_coherence : float
        Smallest probe-phase coherence of the chosen order (0..1).
    alias_tolerance : float
        Candidate orders whose coherence is within this fraction of the best are listed as
        alternatives (the probes cannot tell them apart).
    min_blocks : int
        Consecutive detected blocks (same ND, orders within ``3 / block``) of a detection.
    max_order : float or None
        Largest order searched (None: the blade count).
    """

    block: int = 32
    pad: int = 2
    guard: float = 0.1
    ratio_threshold: float = 10.0
    min_amp_m: float = 5e-6
    min_coherence: float = 0.5
    alias_tolerance: float = 0.05
    min_blocks: int = 2
    max_order: float | None = None

    def __post_init__(self) -> None:
        if int(self.block) < 8:
            raise ValueError(f"NSV block must be >= 8 revolutions, got {self.block}")
        if int(self.pad) < 1:
            raise ValueError(f"NSV pad must be >= 1, got {self.pad}")
        if not 0.0 < self.guard < 0.5:
            raise ValueError(f"NSV guard must be in (0, 0.5), got {self.guard}")
        if int(self.min_blocks) < 1:
            raise ValueError(f"NSV min_blocks must be >= 1, got {self.min_blocks}")


@dataclass(frozen=True, slots=True, eq=False)
class NsvScan:
    """Every block's analysis (detected or not).

    Attributes
    ----------
    start : ndarray of int, shape (n_blocks,)
        First revolution of each block (index into the run); blocks hold ``block`` revolutions.
    block : int
    ratio : ndarray, shape (n_blocks,)
        Detection statistic (peak / median power above the synchronous band).
    alias : ndarray, shape (n_blocks,)
        ``mu``, cycles per revolution, in [guard, 0.5].
    order : ndarray, shape (n_blocks,)
        Best order ``nu`` (NaN where not evaluated: ratio below threshold).
    alternatives : tuple of tuple of (float, int)
        Per block, the other orders the probes cannot tell from ``order``, with their ND.
    coherence : ndarray, shape (n_blocks,)
    nd : ndarray of int, shape (n_blocks,)
        Signed nodal diameter of the wave (0 where not evaluated).
    amp_pkpk_m : ndarray, shape (n_blocks,)
        Pk-pk amplitude of the wave at its ND, m.
    forward_m, backward_m : ndarray, shape (n_blocks, n_nd)
        The travelling-wave spectrum of the block's NSV response by ND, pk-pk, m.
    omega_rad_s : ndarray, shape (n_blocks,)
        Mean speed of the block, rad/s.
    detected : ndarray of bool, shape (n_blocks,)
        The block passes every threshold.
    blade_amp_pkpk_m : ndarray, shape (n_blocks, n_blades)
        Per-blade pk-pk amplitude of the block's NSV response, m.
    whole_run : bool
        A run shorter than ``min_blocks`` blocks (and at least :data:`MIN_WHOLE_RUN`
        revolutions) is one block of all its revolutions; its detection needs no persistence.
    near_sync : ndarray of bool, shape (n_blocks,), or None
        The block's power peak is at the edge of the searched band and not a local maximum
        (the bin below it, in the synchronous band, is as strong): the alias, and with it the
        order's branch and the amplitude, are not resolved (an order passing a whole number).
    """

    start: np.ndarray
    block: int
    ratio: np.ndarray
    alias: np.ndarray
    order: np.ndarray
    alternatives: tuple
    coherence: np.ndarray
    nd: np.ndarray
    amp_pkpk_m: np.ndarray
    forward_m: np.ndarray
    backward_m: np.ndarray
    omega_rad_s: np.ndarray
    detected: np.ndarray
    blade_amp_pkpk_m: np.ndarray
    whole_run: bool = False
    near_sync: np.ndarray | None = None

    @property
    def n_blocks(self) -> int:
        return int(self.start.size)

    @property
    def freq_hz(self) -> np.ndarray:
        """Rotor-frame frequency ``nu Omega / 2 pi`` of each block, Hz."""
        return self.order * self.omega_rad_s / TWO_PI


@dataclass(frozen=True, slots=True, eq=False)
class NsvDetection:
    """One non-synchronous vibration: consecutive detected blocks of one ND.

    Attributes
    ----------
    first_revolution, last_revolution : int
        Revolutions covered (inclusive, numbered as in the run).
    order : float
        ``nu = f / f_shaft`` at the strongest block (the rotor-frame frequency in orders).
    order_alternatives : tuple of float
        Orders the probes could not tell from ``order`` (same alias ``mu``).
    nd_alternatives : tuple of int
        The ND that goes with each alternative order.
    alias : float
        ``mu = |nu - round(nu)|``, cycles per revolution: what one sample per revolution
        shows, unambiguous.
    freq_hz : float
        ``nu Omega / 2 pi`` at the strongest block, Hz; ``freq_min_hz``, ``freq_max_hz`` over
        the blocks.
    nd : int
        Signed nodal diameter (forward positive).
    amp_pkpk_m : float
        Largest block amplitude of the wave at its ND (pk-pk, averaged over the block), m;
        ``amp_first_pkpk_m`` that of the first block (growth); ``amp_last_pkpk_m`` the
        median of the per-revolution amplitudes of the last :data:`LAST_REVOLUTIONS`
        revolutions (the level reached, e.g. a flutter's limit amplitude).
    ratio : float
        Largest detection statistic; ``ratio_threshold`` its threshold.
    coherence : float
        Probe-phase coherence at the strongest block.
    blocks : int
    revolutions : ndarray of int, shape (n,)
        Revolution numbers of the per-revolution amplitudes.
    rev_amp_pkpk_m : ndarray, shape (n,)
        Per revolution, the blade-RMS pk-pk amplitude at the detected order (the growth), m.
    forward_m, backward_m : ndarray, shape (n_nd,)
        Travelling-wave spectrum of the strongest block, pk-pk, m.
    truth : dict or None
        When the run's truth carries its non-synchronous components (:func:`score_nsv`): the
        component matched over the detection's revolutions, ``{"kind", "freq_hz", "nd",
        "amp_pkpk_m", "amp_last_pkpk_m"}`` (``kind`` None: no component was present, a false
        detection).
    """

    first_revolution: int
    last_revolution: int
    order: float
    order_alternatives: tuple
    nd_alternatives: tuple
    alias: float
    freq_hz: float
    freq_min_hz: float
    freq_max_hz: float
    nd: int
    amp_pkpk_m: float
    amp_first_pkpk_m: float
    amp_last_pkpk_m: float
    ratio: float
    ratio_threshold: float
    coherence: float
    blocks: int
    revolutions: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    rev_amp_pkpk_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    forward_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    backward_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth: dict | None = None

    def to_summary(self) -> dict:
        """One element of the summary's ``non_synchronous`` list."""
        return {"kind": "non_synchronous", "order": _num(self.order),
                "order_alternatives": [_num(a) for a in self.order_alternatives],
                "nd_alternatives": [int(n) for n in self.nd_alternatives],
                "alias_per_rev": _num(self.alias), "freq_hz": _num(self.freq_hz),
                "freq_min_hz": _num(self.freq_min_hz), "freq_max_hz": _num(self.freq_max_hz),
                "nd": int(self.nd), "amp_pkpk_m": _num(self.amp_pkpk_m),
                "amp_first_pkpk_m": _num(self.amp_first_pkpk_m), "amp_last_pkpk_m": _num(self.amp_last_pkpk_m),
                "detection": {"statistic": "nsv_peak_to_median_power", "value": _num(self.ratio),
                              "threshold": _num(self.ratio_threshold), "coherence": _num(self.coherence)},
                "revolutions": {"first": int(self.first_revolution), "last": int(self.last_revolution)},
                "blocks": int(self.blocks), **({} if self.truth is None else {"truth": self._truth_summary()})}

    def _truth_summary(self) -> dict:
        """The matched truth component and the errors against it (``nd_correct``,
        ``freq_error_hz``, ``amp_last_error_pct``)."""
        t = self.truth
        if t.get("kind") is None:
            return {"kind": None, "present": False}
        out = {"kind": str(t["kind"]), "present": True, "freq_hz": _num(t["freq_hz"]), "nd": int(t["nd"]),
               "amp_pkpk_m": _num(t["amp_pkpk_m"]), "amp_last_pkpk_m": _num(t["amp_last_pkpk_m"]),
               "nd_correct": int(t["nd"]) == int(self.nd), "freq_error_hz": _num(self.freq_hz - t["freq_hz"])}
        if t["amp_last_pkpk_m"] and math.isfinite(t["amp_last_pkpk_m"]) and math.isfinite(self.amp_last_pkpk_m):
            out["amp_last_error_pct"] = 100.0 * (self.amp_last_pkpk_m - t["amp_last_pkpk_m"]) / t["amp_last_pkpk_m"]
        return out


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _detrend_basis(L: int) -> np.ndarray:
    """Orthonormal columns spanning 1, n, n^2 over a block, shape (L, 3)."""
    n = np.linspace(-1.0, 1.0, L)
    q, _ = np.linalg.qr(np.stack([np.ones(L), n, n * n], axis=1))
    return q


def scan_blocks(d_m, omega_rad_s: np.ndarray, arrival_angles_rad: np.ndarray,
                options: NsvOptions = NsvOptions(), *, starts=None) -> NsvScan:
    """Analyse every whole block of revolutions for a non-synchronous response.

    The blocks are read and transformed in chunks of whole blocks (:data:`NSV_CHUNK`
    samples): the temporaries are bounded by the chunk, not the run; every block's numbers
    are its own (the same as in one pass over the whole run).

    Parameters
    ----------
    d_m : ndarray or row-sliceable object, shape (n_rev, n_blades, n_probes)
        Eq. 1 displacements, m (NaN: missing); offsets need not be removed. Only
        ``d_m.shape`` and row slices ``d_m[a:b]`` (contiguous revolutions, returning an
        ndarray of those rows) are used: a lazy object computing the rows asked for will do
        (e.g. the pipeline's ``_Flat``).
    omega_rad_s : ndarray, shape (n_rev,)
        Mean speed of each revolution, rad/s.
    arrival_angles_rad : ndarray, shape (n_blades, n_probes)
        ``psi_bj``, the rotor angle after the OPR pulse at which blade ``b`` reaches probe
        ``j`` (:meth:`Geometry.nominal_arrival_angles` or the calibrated ones).
    options : NsvOptions
    starts : sequence of int, optional
        First revolutions of the blocks to analyse (default: ``0, L, 2L, ...`` while whole).

    Returns
    -------
    NsvScan
    """
    n_rev, nb, npr = (int(n) for n in d_m.shape)
    L = int(options.block)
    whole = starts is None and MIN_WHOLE_RUN <= n_rev < int(options.min_blocks) * L
    if whole:  # a short run: one block of all of it (persistence cannot be checked)
        L = n_rev
    st = (np.arange(0, n_rev - L + 1, L, dtype=np.int64) if starts is None
          else np.asarray(starts, dtype=np.int64).reshape(-1))
    n_nd = nb // 2 + 1
    nblk = st.size
    out = dict(ratio=np.zeros(nblk), alias=np.full(nblk, np.nan), order=np.full(nblk, np.nan),
               coherence=np.full(nblk, np.nan), nd=np.zeros(nblk, np.int64), amp=np.zeros(nblk),
               fwd=np.zeros((nblk, n_nd)), bwd=np.zeros((nblk, n_nd)), blade=np.zeros((nblk, nb)))
    alternatives: list = [()] * nblk
    idx = st[:, None] + np.arange(L)[None, :]
    om_blk = np.asarray(omega_rad_s, float)[idx].mean(axis=1)
    sp = _spectrum(L, int(options.pad), float(options.guard))
    if nblk == 0 or sp is None:
        return _scan(st, L, out, alternatives, om_blk, np.zeros(nblk, bool), whole)
    n_fft, band, _, _, w_sum = sp
    out["near"] = np.zeros(nblk, bool)
    max_order = float(options.max_order) if options.max_order is not None else float(nb)
    per = max(1, NSV_CHUNK // (L * nb * npr))  # whole blocks per chunk
    for c in range(0, nblk, per):  # chunks of blocks: each block's numbers are its own
        y = _block_rows(d_m, st[c:c + per], L)  # (n, L, nb, npr)
        S, ratio, i_pk, peak = _band_power(y.reshape(y.shape[0], L, nb * npr), sp)
        out["ratio"][c:c + per] = ratio
        k_pk = i_pk + band[0]
        out["near"][c:c + per] = (i_pk == 0) & (S[:, band[0] - 1] >= S[:, band[0]])
        # a rough pk-pk amplitude of the peak (a wave equal on every series): blocks far below
        # the amplitude threshold are not analysed further
        rough = 4.0 * np.sqrt(peak / (nb * npr)) / w_sum
        cand = np.flatnonzero((ratio >= options.ratio_threshold) & (rough >= 0.5 * options.min_amp_m))
        for i in cand:  # few blocks: the ones that may hold an NSV
            k = c + int(i)
            mu0 = _refine(S[i], int(k_pk[i]), n_fft)
            out["alias"][k] = mu0
            coef = _joint_fit(_detrended(y[i][None])[0], mu0)
            Z = coef[4] + 1j * coef[3]  # A exp(i phase) of each blade and probe at the alias, m
            _orders(Z, mu0, arrival_angles_rad, max_order, options, out, alternatives, k)
    ratio = out["ratio"]
    detected = ((ratio >= options.ratio_threshold) & (out["amp"] >= options.min_amp_m)
                & (np.nan_to_num(out["coherence"]) >= options.min_coherence))
    return _scan(st, L, out, alternatives, om_blk, detected, whole)


def _block_rows(d_m, starts: np.ndarray, L: int) -> np.ndarray:
    """The revolutions of the blocks starting at ``starts``, shape (n, L, nb, npr), float, read
    from ``d_m`` as row slices only: one slice when the blocks follow one another (the
    default blocks), else one per block."""
    lo = int(starts[0])
    if np.array_equal(starts, lo + L * np.arange(starts.size)):
        x = np.asarray(d_m[lo:lo + L * starts.size], dtype=float)
        return x.reshape(starts.size, L, *x.shape[1:])
    return np.stack([np.asarray(d_m[int(s):int(s) + L], dtype=float) for s in starts])


def _band_power(y: np.ndarray, sp: tuple) -> tuple:
    """Power summed over the series at each bin, and the detection statistic, of blocks
    ``y`` (n_blocks, L, n_series) (NaN: missing, takes its series' mean): ``(S, ratio, i_pk,
    peak)`` with ``S`` (n_blocks, n_fft // 2 + 1) (0 outside the computed bins), the
    peak-to-median ratio over the band, the peak's index in the band and its power."""
    n_fft, band, comp, M, _ = sp
    if not np.isfinite(y).all():
        ok = np.isfinite(y)
        with np.errstate(all="ignore"):
            mean = np.where(ok, y, 0.0).sum(axis=1, keepdims=True) / np.maximum(ok.sum(axis=1, keepdims=True), 1)
        y = np.where(ok, y, mean)
    # the power summed over the series at a bin is m^T (sum_s y_s y_s^T) m for its real and
    # imaginary rows m of M: one L x L matrix per block instead of a spectrum per series
    y = y - y.mean(axis=1, keepdims=True)  # (M removes it anyway) less cancellation in C
    C = np.matmul(y, np.swapaxes(y, 1, 2))  # (n_blocks, L, L)
    P = np.maximum(np.einsum("lf,klf->kf", M, C @ M), 0.0)  # (n_blocks, 2 n_comp); rounding can go below 0
    nbd = comp.size
    S = np.zeros((y.shape[0], n_fft // 2 + 1))
    S[:, comp] = P[:, :nbd] + P[:, nbd:]
    Sb = S[:, band]
    half = Sb.shape[1] // 2
    floor = np.partition(Sb, half, axis=1)[:, half]  # the (upper) median
    i_pk = np.argmax(Sb, axis=1)
    peak = Sb[np.arange(Sb.shape[0]), i_pk]
    with np.errstate(all="ignore"):
        ratio = np.where(floor > 0, peak / floor, np.where(peak > 0, np.inf, 0.0))
    return S, ratio, i_pk, peak


def screen_block(d_m: np.ndarray, options: NsvOptions = NsvOptions(), *, finite: bool = False) -> bool:
    """Whether one block ``d_m`` (L, n_blades, n_probes) may hold an NSV: the detection
    statistic and the rough amplitude of :func:`scan_blocks`'s first step, without the rest
    (the live processor scans a block in full only then).

    The same operations as :func:`_band_power` on one block, without the parts the screen
    does not read (the spectrum outside the band, the peak's bin); ``finite``: the caller
    knows every sample is finite (the check for missing ones is skipped)."""
    d = np.asarray(d_m, dtype=float)
    L = d.shape[0]
    sp = _spectrum(L, int(options.pad), float(options.guard))
    if sp is None:
        return False
    y = d.reshape(1, L, -1)
    if not finite and not np.isfinite(y).all():  # missing samples: the general code
        _, ratio, _, peak = _band_power(y, sp)
        ratio, peak = float(ratio[0]), float(peak[0])
    else:
        _, _, _, M, _ = sp
        y = y - np.add.reduce(y, axis=1, keepdims=True) / L  # y.mean(axis=1, keepdims=True)
        C = np.matmul(y, np.swapaxes(y, 1, 2))
        P = np.maximum(np.einsum("lf,klf->kf", M, C @ M), 0.0)[0]
        nbd = P.size // 2
        Sb = (P[:nbd] + P[nbd:])[1:]  # S at the band (comp is one bin below it, then the band)
        half = Sb.size // 2
        floor = float(np.partition(Sb, half)[half])
        peak = float(Sb[np.argmax(Sb)])
        ratio = peak / floor if floor > 0 else (math.inf if peak > 0 else 0.0)
    rough = 4.0 * math.sqrt(peak / (d.shape[1] * d.shape[2])) / sp[4]
    return bool(ratio >= options.ratio_threshold and rough >= 0.5 * options.min_amp_m)


def _scan(st, L, out, alternatives, om_blk, detected, whole) -> NsvScan:
    return NsvScan(start=st, block=L, whole_run=bool(whole), ratio=out["ratio"], alias=out["alias"], order=out["order"],
                   alternatives=tuple(alternatives), coherence=out["coherence"], nd=out["nd"],
                   amp_pkpk_m=out["amp"], forward_m=out["fwd"], backward_m=out["bwd"], omega_rad_s=om_blk,
                   detected=np.asarray(detected, bool), blade_amp_pkpk_m=out["blade"],
                   near_sync=out.get("near", np.zeros(st.size, bool)))


def _spectrum(L: int, pad: int, guard: float):
    """The searched band of a block of ``L`` revolutions and its spectrum matrix (cached):
    ``(n_fft, band, comp, M, w_sum)`` with ``band`` the searched bins (aliases from
    ``max(guard, 2.5 / L)``, beyond the Hann main lobe of the synchronous band), ``comp`` the
    computed ones (one more below, for the refinement), ``M`` (L, 2 n_comp) the trend
    removal ``I - Q Q^T``, the Hann window and the zero-padded DFT at ``comp`` as one real
    matrix (a series ``x`` gives ``[Re X, Im X] = x @ M``) and ``w_sum`` the window's sum.
    None when the band has fewer than 3 bins."""
    key = (L, pad, guard)
    if key not in _SPECTRA:
        n_fft = pad * L
        mu = np.arange(n_fft // 2 + 1) / n_fft
        band = np.flatnonzero(mu >= max(guard, 2.5 / L))
        if band.size < 3:
            _SPECTRA[key] = None
            return None
        comp = np.concatenate([band[:1] - 1, band])
        Q = _detrend_basis(L)
        w = np.hanning(L + 2)[1:-1]
        A = w[:, None] * (np.eye(L) - Q @ Q.T)  # (L, L): windowed detrended = A @ x
        F = np.exp(-2j * np.pi * np.outer(comp, np.arange(L)) / n_fft)  # (n_comp, L)
        FA = F @ A
        M = np.ascontiguousarray(np.concatenate([FA.real, FA.imag], axis=0).T)
        _SPECTRA[key] = (n_fft, band, comp, M, float(w.sum()))
    return _SPECTRA[key]


_SPECTRA: dict = {}


def _detrended(x: np.ndarray) -> np.ndarray:
    """Blocks ``(nblk, L, nb, npr)`` with each series' quadratic trend removed; missing
    samples (NaN) become 0 after the removal of the series mean."""
    L = x.shape[1]
    ok = np.isfinite(x)
    if ok.all():
        y = x
    else:
        with np.errstate(all="ignore"):
            cnt = ok.sum(axis=1, keepdims=True)
            mean = np.where(cnt > 0, np.where(ok, x, 0.0).sum(axis=1, keepdims=True) / np.maximum(cnt, 1), 0.0)
        y = np.where(ok, x, mean)
    Q = _detrend_basis(L)
    coef = np.einsum("nq,knbj->kqbj", Q, y)
    y = y - np.einsum("nq,kqbj->knbj", Q, coef)
    return np.where(ok, y, 0.0)


def _refine(S: np.ndarray, k: int, n_fft: int) -> float:
    """Alias of the power peak at bin ``k``, refined by a parabola through the log power."""
    if 0 < k < S.size - 1 and np.all(S[k - 1:k + 2] > 0):
        a, b, c = np.log(S[k - 1:k + 2])
        den = a - 2 * b + c
        delta = 0.5 * (a - c) / den if den < 0 else 0.0
        return float(np.clip((k + np.clip(delta, -0.5, 0.5)) / n_fft, 0.0, 0.5))
    return float(k / n_fft)


def _joint_basis(L: int, mu: float) -> np.ndarray:
    """Columns 1, n, n^2, cos(2 pi mu n), sin(2 pi mu n) over a block, shape (L, 5)."""
    n = np.arange(L)
    t = np.linspace(-1.0, 1.0, L)
    return np.stack([np.ones(L), t, t * t, np.cos(TWO_PI * mu * n), np.sin(TWO_PI * mu * n)], axis=1)


def _joint_fit(x: np.ndarray, mu: float) -> np.ndarray:
    """Least-squares coefficients of :func:`_joint_basis` for each blade and probe series of
    one block ``x`` (L, nb, npr), shape (5, nb, npr): the quadratic trend and the sinusoid at
    the alias together (removing the trend alone would take part of the sinusoid)."""
    pinv = np.linalg.pinv(_joint_basis(x.shape[0], mu), rcond=1e-8)
    return np.einsum("qn,nbj->qbj", pinv, x)


def _orders(Z: np.ndarray, mu0: float, psi: np.ndarray, max_order: float, options: NsvOptions,
            out: dict, alternatives: list, k: int) -> None:
    """Score the orders ``m +- mu0`` by probe-phase coherence; the best one's ND, spectrum
    and amplitude into ``out[...][k]``."""
    nb, npr = Z.shape
    n_m = int(math.ceil(max_order)) + 2
    m = np.arange(n_m)
    nus = np.concatenate([m + mu0, m - mu0])
    keep = (nus > 0) & (nus <= max_order)
    if not keep.any():
        return
    present = np.abs(Z) > 0
    # exp(-i (m +- mu) psi) = exp(-i m psi) exp(-+ i mu psi): the whole orders' table is cached
    E = _whole_order_phases(psi, n_m)  # (n_m, nb, npr)
    e_mu = np.exp(-1j * mu0 * psi) * present
    Y = np.concatenate([np.einsum("mbj,bj->mb", E, Z * e_mu),  # branch +: nu = m + mu
                        np.einsum("mbj,bj->mb", E, np.conj(Z * e_mu))])[keep]  # branch -: conj(Z) exp(+i mu psi)
    nus = nus[keep]
    n_p = np.maximum(present.sum(axis=1), 1)
    total = float(np.sum(np.abs(Z) ** 2))
    if total <= 0:
        return
    coh = np.sum(np.abs(Y) ** 2 / n_p[None, :], axis=1) / total
    best = int(np.argmax(coh))
    near = [i for i in np.flatnonzero(coh >= coh[best] * (1.0 - options.alias_tolerance)) if i != best]
    out["order"][k] = float(nus[best])
    out["coherence"][k] = float(coh[best])
    q = 2.0 * Y[best] / n_p  # complex pk-pk response of each blade, ND phase only
    out["blade"][k] = np.abs(q)
    fwd, bwd, nd, amp = _wave(q)
    out["fwd"][k], out["bwd"][k], out["nd"][k], out["amp"][k] = fwd, bwd, nd, amp
    alternatives[k] = tuple((float(nus[i]), _wave(2.0 * Y[i] / n_p)[2]) for i in near)


def _whole_order_phases(psi: np.ndarray, n_m: int) -> np.ndarray:
    """``exp(-i m psi)`` for ``m = 0 .. n_m - 1``, shape (n_m, nb, npr), cached per arrival angles."""
    key = (psi.tobytes(), psi.shape, n_m)
    if key not in _PHASES:
        if len(_PHASES) > 8:
            _PHASES.clear()
        _PHASES[key] = np.exp(-1j * np.arange(n_m)[:, None, None] * np.asarray(psi, float)[None])
    return _PHASES[key]


_PHASES: dict = {}


def _wave(q: np.ndarray) -> tuple:
    """Forward / backward pk-pk magnitudes by ND of per-blade complex pk-pk responses, the
    signed ND of the largest and its magnitude."""
    nb = q.size
    Q = np.fft.fft(q) / nb
    nd = np.arange(nb // 2 + 1)
    fwd, bwd = np.abs(Q[nd % nb]), np.abs(Q[(-nd) % nb])
    i_f, i_b = int(np.argmax(fwd)), int(np.argmax(bwd))
    return fwd, bwd, (-i_b if bwd[i_b] > fwd[i_f] else i_f), float(max(fwd[i_f], bwd[i_b]))


def detections(scan: NsvScan, d_m, arrival_angles_rad: np.ndarray, options: NsvOptions = NsvOptions(),
               *, revolution0: int = 0, omega_rad_s: np.ndarray | None = None) -> tuple:
    """Group detected blocks into detections (runs of ``min_blocks`` consecutive blocks of one
    ND and orders within ``3 / block``), with the per-revolution amplitude growth.

    ``d_m`` (n_rev, n_blades, n_probes), as for :func:`scan_blocks` (an ndarray or an object
    with row slices): only the revolutions of the detections' resolved blocks are read, one
    block ``d_m[s:s + block]`` at a time (:func:`revolution_amplitudes`).

    With ``omega_rad_s`` (n_rev,), each block's frequency is its order times the speed
    averaged with the per-revolution amplitudes squared as weights (where the vibration is:
    a flutter at a fixed frequency changes its order while the speed moves); otherwise the
    block's mean speed.

    Returns
    -------
    tuple of NsvDetection
    """
    near = np.zeros(scan.n_blocks, bool) if scan.near_sync is None else np.asarray(scan.near_sync, bool)
    out = []
    omega = None if omega_rad_s is None else np.asarray(omega_rad_s, float)
    for run in _group_blocks(scan, near):
        if len(run) < int(options.min_blocks) and not scan.whole_run:
            continue
        # the blocks whose alias is resolved give the order, frequency and per-revolution
        # amplitudes (all of them when none is)
        resolved = [k for k in run if not near[k]] or run
        r = np.asarray(resolved)
        top = int(r[np.argmax(scan.amp_pkpk_m[r])])
        revs, amps, f = [], [], []
        for k in resolved:
            s = int(scan.start[k])
            revs.append(np.arange(s, s + scan.block))
            a = revolution_amplitudes(np.asarray(d_m[s:s + scan.block], dtype=float), arrival_angles_rad,
                                      float(scan.order[k]), float(scan.alias[k]))
            amps.append(a)
            w = np.nan_to_num(a) ** 2
            if omega is not None and w.sum() > 0:
                om = float(np.sum(w * omega[s:s + scan.block]) / w.sum())
            else:
                om = float(scan.omega_rad_s[k])
            f.append(float(scan.order[k]) * om / TWO_PI)
        f = np.asarray(f)
        rev_amp = np.concatenate(amps)
        last = rev_amp[-LAST_REVOLUTIONS:]
        last_amp = float(np.median(last[np.isfinite(last)])) if np.isfinite(last).any() else math.nan
        out.append(NsvDetection(
            first_revolution=revolution0 + int(scan.start[run[0]]),
            last_revolution=revolution0 + int(scan.start[run[-1]]) + scan.block - 1,
            order=float(scan.order[top]), order_alternatives=tuple(o for o, _ in scan.alternatives[top]),
            nd_alternatives=tuple(n for _, n in scan.alternatives[top]), alias=float(scan.alias[top]),
            freq_hz=float(f[resolved.index(top)]), freq_min_hz=float(np.min(f)), freq_max_hz=float(np.max(f)),
            nd=int(scan.nd[top]), amp_pkpk_m=float(scan.amp_pkpk_m[top]),
            amp_first_pkpk_m=float(scan.amp_pkpk_m[r[0]]), amp_last_pkpk_m=last_amp,
            ratio=float(np.max(scan.ratio[np.asarray(run)])),
            ratio_threshold=float(options.ratio_threshold), coherence=float(scan.coherence[top]), blocks=len(run),
            revolutions=revolution0 + np.concatenate(revs), rev_amp_pkpk_m=rev_amp,
            forward_m=scan.forward_m[top].copy(), backward_m=scan.backward_m[top].copy()))
    return tuple(out)


def _same_wave(scan: NsvScan, k: int, j: int, tol: float, predicted: float | None = None) -> bool:
    """Block ``k``'s order within ``tol`` of block ``j``'s (or of ``predicted``), or of one
    block ``j`` could not be told from, with the ND that goes with it."""
    ref = ((scan.order[j] if predicted is None else predicted, scan.nd[j]), *scan.alternatives[j])
    return any(abs(scan.order[k] - o) <= tol and scan.nd[k] == n for o, n in ref)


def _bridges(scan: NsvScan, run: list, k: int, tol: float, near: np.ndarray) -> bool:
    """Whether resolved block ``k`` continues ``run`` across blocks where the order passed a
    whole or half number (near-synchronous or undetected blocks in between): the same ND, such
    a number between the orders (or next to one), and ``k``'s order where the run's last
    resolved blocks' trend puts it, within a gap no longer than that trend needs to cross the
    unresolved band (at least 4 blocks)."""
    res = [j for j in run if not near[j]]
    if not res:
        return False
    j = res[-1]
    steps = int(scan.start[k] - scan.start[j]) // scan.block
    rate = 0.0
    if len(res) > 1:
        span = max(int(scan.start[j] - scan.start[res[-2]]) // scan.block, 1)
        rate = float(scan.order[j] - scan.order[res[-2]]) / span
    edge = float(np.nanmin(scan.alias[np.asarray(res)])) + tol
    max_steps = min(64, max(4, int(math.ceil(2.0 * edge / abs(rate))) + 2 if rate else 4))
    a, b = float(scan.order[j]), float(scan.order[k])
    # a whole order (alias 0: the synchronous band) or a half one (alias 0.5: the two
    # branches m + 1/2 and m + 1 - 1/2 coincide) between them, or next to one of them
    crosses = (math.floor(2.0 * a) != math.floor(2.0 * b)
               or min(abs(2.0 * x - round(2.0 * x)) for x in (a, b)) <= 2.0 * edge)
    return (1 < steps <= max_steps and crosses and scan.nd[k] == scan.nd[j]
            and _same_wave(scan, k, j, 2.0 * tol, predicted=a + rate * steps))


def _group_blocks(scan: NsvScan, near: np.ndarray) -> list[list[int]]:
    """The detected blocks grouped into vibrations: consecutive blocks whose orders are within
    ``3 / block`` (or of an order the last block could not be told from, the ND going with
    it). A near-synchronous block (``scan.near_sync``: its alias unresolved, next to a whole
    order) joins the run before it when its ND matches and at most one block lies between;
    a resolved block continues a run across such blocks when the order passed a whole number
    (:func:`_bridges`): one continuous vibration is one detection."""
    runs: list[list[int]] = []
    tol = 3.0 / scan.block
    for k in (int(i) for i in np.flatnonzero(scan.detected)):
        run = runs[-1] if runs else None
        last = run[-1] if run else None
        steps = None if last is None else int(scan.start[k] - scan.start[last]) // scan.block
        if steps == 1 and _same_wave(scan, k, last, tol):
            run.append(k)
        elif near[k] and steps is not None and steps <= 2 and scan.nd[k] == scan.nd[last]:
            run.append(k)
        elif run is not None and not near[k] and _bridges(scan, run, k, tol, near):
            run.append(k)
        else:
            runs.append([k])
    return runs


def revolution_amplitudes(d_m: np.ndarray, arrival_angles_rad: np.ndarray, order: float,
                          alias: float) -> np.ndarray:
    """Per revolution of one block, the blade-RMS pk-pk amplitude of the response at ``order``.

    Each blade and probe series loses its quadratic trend (fitted jointly with the sinusoid
    at ``alias`` whose amplitude may change linearly over the block); each blade's samples of
    a revolution are then fitted by least squares with ``sin(nu psi_bj)`` and
    ``cos(nu psi_bj)``.

    Parameters
    ----------
    d_m : ndarray, shape (L, n_blades, n_probes)
    arrival_angles_rad : ndarray, shape (n_blades, n_probes)
    order : float

    Returns
    -------
    ndarray, shape (L,)
    """
    x = _detrended(np.asarray(d_m, float)[None])[0]  # (L, nb, npr)
    L = x.shape[0]
    t = np.linspace(-1.0, 1.0, L)[:, None]
    B = _joint_basis(L, alias)
    B = np.concatenate([B, t * B[:, 3:5]], axis=1)  # the sinusoid's amplitude may change (growth)
    coef = np.einsum("qn,nbj->qbj", np.linalg.pinv(B, rcond=1e-8), x)
    x = x - np.einsum("nq,qbj->nbj", B[:, :3], coef[:3])
    ok = np.isfinite(np.asarray(d_m, float))
    arg = float(order) * np.asarray(arrival_angles_rad, float)
    s, c = np.sin(arg)[None] * ok, np.cos(arg)[None] * ok  # (L, nb, npr)
    ss, sc, cc = (s * s).sum(-1), (s * c).sum(-1), (c * c).sum(-1)
    rs, rc = (s * x).sum(-1), (c * x).sum(-1)
    with np.errstate(all="ignore"):
        det = ss * cc - sc * sc
        a1 = (cc * rs - sc * rc) / det
        a2 = (ss * rc - sc * rs) / det
        amp = 2.0 * np.hypot(a1, a2)
        amp = np.where((ok.sum(-1) >= 3) & (det > 1e-9), amp, np.nan)
        sq = amp * amp
        n = np.count_nonzero(~np.isnan(sq), axis=1)
        # np.nanmean without its warning for a blade with no fit: NaN there
        return np.sqrt(np.where(n > 0, np.nansum(sq, axis=1) / np.maximum(n, 1), np.nan))


def detect_nsv(d_m, omega_rad_s: np.ndarray, arrival_angles_rad: np.ndarray,
               options: NsvOptions = NsvOptions(), *, revolution0: int = 0) -> tuple[NsvScan, tuple]:
    """:func:`scan_blocks` then :func:`detections`: the block analysis and the detections.

    ``d_m`` (n_rev, n_blades, n_probes): an ndarray, or any object with ``.shape`` and row
    slices ``d_m[a:b]`` returning an ndarray of those revolutions (e.g. computed on demand):
    :func:`scan_blocks` reads it in chunks of whole blocks (:data:`NSV_CHUNK` samples),
    :func:`detections` one detected block at a time; neither holds a run-sized copy."""
    scan = scan_blocks(d_m, omega_rad_s, arrival_angles_rad, options)
    return scan, detections(scan, d_m, arrival_angles_rad, options, revolution0=revolution0, omega_rad_s=omega_rad_s)


@dataclass(frozen=True, slots=True, eq=False)
class NsvTruthRows:
    """The truth's non-synchronous components per revolution (the simulator's ``Truth.nsv_*``).

    Attributes
    ----------
    kind : ndarray of str, shape (n_rev, k)
        ``"rotating_stall"``, ``"flutter"``, ``"broadband"`` ("" where unknown).
    freq_hz : ndarray, shape (n_rev, k)
        Rotor-frame frequency, Hz (NaN: no truth for that revolution).
    nd : ndarray of int, shape (n_rev, k)
        Signed ND (the :mod:`.travelling_wave` convention).
    amp_pkpk_m : ndarray, shape (n_rev, k)
        Pk-pk amplitude at P_nom (0: absent in that revolution), m.
    """

    kind: np.ndarray
    freq_hz: np.ndarray
    nd: np.ndarray
    amp_pkpk_m: np.ndarray


def nsv_truth_rows(truth, n_rev: int) -> NsvTruthRows | None:
    """The NSV truth of a Truth-like object (``nsv_kind``, ``nsv_freq_hz``, ``nsv_nd``,
    ``nsv_amp_pkpk_m``, each (n_rev, k)), or None when it has none (or of another length)."""
    arrays = [getattr(truth, f"nsv_{n}", None) for n in ("kind", "freq_hz", "nd", "amp_pkpk_m")]
    if truth is None or any(a is None for a in arrays):
        return None
    kind, freq, nd, amp = (np.asarray(a) for a in arrays)
    if kind.ndim != 2 or kind.shape[0] != n_rev or not all(a.shape == kind.shape for a in (freq, nd, amp)):
        return None
    return NsvTruthRows(kind=kind.astype(str), freq_hz=freq.astype(float), nd=nd.astype(np.int64),
                        amp_pkpk_m=amp.astype(float))


def score_nsv(det: NsvDetection, truth: NsvTruthRows, revolution0: int = 0) -> dict:
    """The truth component that a detection found: over the detection's revolutions, among the
    components present (amplitude above 0), the one with the detected ND, else the nearest in
    frequency. ``kind`` None when none was present (a false detection).

    Returns
    -------
    dict
        ``{"kind", "freq_hz" (mean where present), "nd", "amp_pkpk_m" (largest),
        "amp_last_pkpk_m"}``: the median at the revolutions of the detection's
        ``amp_last_pkpk_m`` (its last :data:`LAST_REVOLUTIONS` per-revolution amplitudes;
        without them, the component's last revolutions present in the detection's span).
    """
    n_rev = truth.freq_hz.shape[0]
    lo = max(int(det.first_revolution) - revolution0, 0)
    hi = min(int(det.last_revolution) - revolution0 + 1, n_rev)
    revs = np.asarray(det.revolutions, np.int64)[np.isfinite(np.asarray(det.rev_amp_pkpk_m, float))]
    rows = revs[-LAST_REVOLUTIONS:] - int(revolution0)
    rows = rows[(rows >= 0) & (rows < n_rev)]
    best, key = None, None
    for c in range(truth.freq_hz.shape[1]):
        amp = truth.amp_pkpk_m[lo:hi, c]
        present = np.isfinite(amp) & (amp > 0) & np.isfinite(truth.freq_hz[lo:hi, c])
        if not present.any():
            continue
        f = float(np.mean(truth.freq_hz[lo:hi, c][present]))
        nds, counts = np.unique(truth.nd[lo:hi, c][present], return_counts=True)
        nd = int(nds[np.argmax(counts)])
        k = (nd != int(det.nd), abs(f - float(det.freq_hz)))
        if key is None or k < key:
            last = truth.amp_pkpk_m[rows, c] if rows.size else amp[present][-LAST_REVOLUTIONS:]
            last = last[np.isfinite(last)] if np.isfinite(last).any() else amp[present][-LAST_REVOLUTIONS:]
            best, key = {"kind": str(truth.kind[lo:hi, c][present][0]), "freq_hz": f, "nd": nd,
                         "amp_pkpk_m": float(np.max(amp[present])), "amp_last_pkpk_m": float(np.median(last))}, k
    return best if best is not None else {"kind": None}


def _nd_text(nd: int) -> str:
    return f"ND {nd:+d} ({'forward' if nd > 0 else 'backward' if nd < 0 else 'standing'})"


def is_rigid_body(det: NsvDetection) -> bool:
    """Is a detection the rotor's own angular motion rather than blade vibration: ND 0 (every
    blade the same) at an order below 1 (slower than the shaft in the rotor frame; no order the
    probes could not tell from it)? A speed fluctuation, shaft torsion or OPR timing moves
    every blade's arrival alike, and Eq. 1 turns that into this pattern; a blade's own modes lie
    far above the shaft frequency."""
    return int(det.nd) == 0 and abs(float(det.order)) < 1.0 and not det.order_alternatives


def rigid_body_note(det: NsvDetection) -> str:
    """The note that replaces a rigid-body detection (:func:`is_rigid_body`) in the report."""
    return (f"rigid-body motion, not blade vibration: ND 0 content at {det.freq_hz:.2f} Hz in the rotor frame (order "
            f"{det.order:.3f}, slower than the shaft), the same on every blade, {1e3 * det.amp_pkpk_m:.4f} mm pk-pk, "
            f"revolutions {det.first_revolution}-{det.last_revolution}: the rotor turning unevenly against its OPR "
            f"pulse (a speed fluctuation, shaft torsion, OPR timing), which Eq. 1 cannot tell from a vibration; not "
            f"reported as non-synchronous vibration")


def nsv_note(det: dict) -> str:
    """One sentence on a detection (a ``non_synchronous`` summary element)."""
    alts = list(zip(det.get("order_alternatives") or [], det.get("nd_alternatives") or []))
    alt = (f" (or {', '.join(f'{a:.3f} with ND {n:+d}' for a, n in alts)}: the probes cannot tell these apart)"
           if alts else "")
    rev = det["revolutions"]
    return (f"non-synchronous vibration (not an engine-order resonance) at order {det['order']:.3f}{alt}, "
            f"{det['freq_hz']:.2f} Hz, alias {det['alias_per_rev']:.3f} cycles/rev, {_nd_text(det['nd'])}, "
            f"{1e3 * det['amp_pkpk_m']:.4f} mm pk-pk, revolutions {rev['first']}-{rev['last']}")


def nsv_table_lines(summary: dict) -> list[str]:
    """Printed lines for the summary's ``non_synchronous`` detections."""
    lines = []
    for det in summary.get("non_synchronous", []) or []:
        d = det["detection"]
        lines.append(f"NON-SYNCHRONOUS VIBRATION  order {det['order']:.3f}"
                     + (" (or " + ", ".join(f"{a:.3f} with ND {n:+d}" for a, n in
                                             zip(det["order_alternatives"], det["nd_alternatives"]))
                        + ": the probes cannot tell these apart)" if det.get("order_alternatives") else "")
                     + f"  alias {det['alias_per_rev']:.3f}/rev  {det['freq_hz']:.2f} Hz "
                     f"({det['freq_min_hz']:.2f}-{det['freq_max_hz']:.2f})  {_nd_text(det['nd'])}  "
                     f"{1e3 * det['amp_pkpk_m']:.4f} mm pk-pk (first block {1e3 * det['amp_first_pkpk_m']:.4f}, "
                     f"last revolutions {1e3 * (det.get('amp_last_pkpk_m') or 0.0):.4f})  "
                     f"revolutions {det['revolutions']['first']}-{det['revolutions']['last']}  "
                     f"power ratio {d['value']:.3g} (>= {d['threshold']:g}), coherence {d['coherence']:.3f}")
        t = det.get("truth")
        if t is not None:
            if not t.get("present"):
                lines.append("  truth: no non-synchronous component in these revolutions (a false detection)")
            else:
                err = f", level error {t['amp_last_error_pct']:+.1f} %" if "amp_last_error_pct" in t else ""
                lines.append(f"  truth: {t['kind']} {t['freq_hz']:.2f} Hz {_nd_text(t['nd'])} "
                             f"{1e3 * t['amp_last_pkpk_m']:.4f} mm pk-pk (last revolutions): ND "
                             f"{'correct' if t['nd_correct'] else 'WRONG'}, frequency error "
                             f"{t['freq_error_hz']:+.3f} Hz{err}")
    return lines
