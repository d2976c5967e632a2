"""The streaming processor: OPR + TOAs in one revolution at a time, per-revolution fits and
travelling waves out, and the offline pipeline's report at the end.

:class:`StreamingProcessor` is fed one revolution at a time (OPR time and the
``(n_blades, n_probes)`` TOAs); each :meth:`~StreamingProcessor.push` returns the
per-revolution outputs that became computable, one revolution late (revolution ``n`` needs
OPR ``n + 1`` for its speed), and :meth:`~StreamingProcessor.finish` runs the offline
pipeline (:func:`~.pipeline.process_arrays`) over the stored TOAs for the final resonance
report, so the report is identical to the offline one. While the run streams its memory does
not grow with the run (:mod:`.history`): the TOAs are kept in a scratch file but for the
latest few MB, the live displacements only as far back as they are read.

The per-revolution fits are computed on the displacements as they come (no smoothing, which
would need future revolutions), with the nominal blade geometry until the calibration window
is complete and calibrated arrival angles afterwards. Eq. 1 is
:func:`~.displacement.revolution_displacements` (the offline displacements bit for bit);
the fits and spectra of a complete revolution are a few precomputed matrix products.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .displacement import TWO_PI, Geometry, calibrate_arrival_angles, outside_revolution, revolution_displacements, \
    rotor_phase_from_opr
from .fit import WindowFit, design_matrix, fit_revolutions
from .history import RecentRows, SpilledRows
from .nsv import NsvDetection, detections, is_rigid_body, scan_blocks, screen_block
from .options import LIVE_CALIBRATION, ProcessOptions, engine_orders_of, fits_jointly, layout_condition_numbers
from .pipeline import process_arrays
from .results import ProcessingResult, RevolutionOutput
from .travelling_wave import TravellingWaveSpectra, fit_spectra, probe_spectra

__all__ = ["StreamingProcessor"]



class _Growable:
    """An array that grows along axis 0 by doubling."""

    def __init__(self, shape_tail: tuple, capacity: int = 1024) -> None:
        self._a = np.full((max(capacity, 4),) + shape_tail, np.nan)
        self.n = 0

    def append(self, row) -> None:
        if self.n == self._a.shape[0]:
            self._a = np.concatenate([self._a, np.full_like(self._a, np.nan)])
        self._a[self.n] = row
        self.n += 1

    def next_row(self) -> np.ndarray:
        """Append a row (NaN) and return it, to be written in place."""
        if self.n == self._a.shape[0]:
            self._a = np.concatenate([self._a, np.full_like(self._a, np.nan)])
        self.n += 1
        return self._a[self.n - 1]

    def __getitem__(self, i):
        return self._a[: self.n][i]

    def row(self, k: int):
        """Row ``k`` (``0 <= k < n``, unchecked): ``self[k]`` without the slice."""
        return self._a[k]

    @property
    def array(self) -> np.ndarray:
        return self._a[: self.n]


class StreamingProcessor:
    """Process a stream revolution by revolution.

    Parameters
    ----------
    info : Geometry, RunInfo or RunMetadataMsg
    options : ProcessOptions
        ``expected_times`` must be ``"opr"`` (a stream carries no exact expected times).

    Notes
    -----
    Latency: the outputs of revolution ``n`` come out of ``push`` of revolution
    ``n + 1 + window // 2`` (:attr:`latency_revolutions`; revolution 0 waits one more for the
    acceleration of revolution 1, as offline). A gap in the revolution numbers
    (lost messages) is filled with revolutions without arrivals and interpolated OPR times.

    Examples
    --------
    >>> proc = StreamingProcessor(info)                       # doctest: +SKIP
    >>> for n, opr, toa in stream:                            # doctest: +SKIP
    ...     for out in proc.push(n, opr, toa):
    ...         publish(out)
    >>> for out in proc.flush(): publish(out)                 # doctest: +SKIP
    >>> summary = proc.finish(truth_peaks)                    # doctest: +SKIP
    """

    def __init__(self, info, options: ProcessOptions = ProcessOptions()) -> None:
        if options.expected_times != "opr":
            raise ValueError('the streaming processor uses OPR-based expected times (expected_times="opr")')
        self.info = info
        self.options = options
        self.geometry = Geometry.from_info(info)
        # LayoutError if an order is singular
        eos, _, _ = layout_condition_numbers(engine_orders_of(info, options), self.geometry, False)
        if len(eos) > 1 and not fits_jointly(eos, self.geometry):
            eos = eos[:1]  # the live fits cannot hold them jointly: the first order (the report has them all)
        self.engine_orders = eos
        g = self.geometry
        self._shape = (g.n_blades, g.n_probes)
        cap = int(getattr(info, "n_revolutions", 0) or 0) + 8
        self._opr = _Growable((), cap)
        # the TOAs for the final report: the recent revolutions in memory, the others in a
        # scratch file; the live displacements and speeds only as far back as they are used
        self._toa = SpilledRows(self._shape)
        self._d = RecentRows(self._shape)
        self._omega = RecentRows()
        self._was_calibrated = RecentRows(dtype=bool, fill=False)
        self._row_sum = RecentRows()  # per revolution, the sum of the displacements (NaN: one is missing)
        self._first_rev: int | None = None
        self._n_done = 0  # displacements computed for revolutions [0, _n_done)
        self._n_emitted = 0
        cal = options.calibration
        if isinstance(cal, str):  # "auto": the final report chooses; the live outputs use the start
            cal = LIVE_CALIBRATION
        if not cal:
            self._cal_window = None
        elif isinstance(cal, (int, np.integer)):
            self._cal_window = (0, int(cal))
        else:
            self._cal_window = (int(cal[0]), int(cal[1]))
        self._psi = g.nominal_arrival_angles()
        self._calibrated = False
        self._window = int(options.window)
        self.latency_revolutions = 1 + self._window // 2
        B = design_matrix(g.probe_angles_rad, self.engine_orders)
        self._B = B
        self._pinv = np.linalg.pinv(B) if B.shape[0] >= B.shape[1] else None
        gi = np.linalg.inv(B.T @ B) if self._pinv is not None else None
        i1 = np.arange(1, B.shape[1], 2)
        self._i1 = i1
        self._ginv = None if gi is None else (gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1])
        self._g12x2 = None if gi is None else 2.0 * gi[i1, i1 + 1]
        # the same terms as columns (n_eo, 1), for the (order, blade) rows of _output
        self._ginv_col = None if gi is None else tuple(g[:, None] for g in (*self._ginv[:2], self._g12x2))
        self._g1122_col = None if gi is None else _interleave(*self._ginv_col[:2])
        self._cn = float(np.linalg.cond(B))
        self._eo_arr = np.asarray(self.engine_orders, float)
        npr, p = B.shape
        self._pinvT = None if self._pinv is None else np.ascontiguousarray(self._pinv.T)
        self._BT = np.ascontiguousarray(B.T)
        self._inv_dof = 1.0 / (npr - p) if npr > p else math.nan
        self._residual = None if self._pinv is None else np.eye(npr) - self._pinv.T @ B.T
        self._freq_per_omega = self._eo_arr / TWO_PI
        self._F_probe, self._F_fit, self._n_nd = _spectrum_matrices(g, self.engine_orders[0])
        # the windowed fits (window > 1) with the design matrix's inverses computed once
        self._wfit = WindowFit(g.probe_angles_rad, self.engine_orders, self._window) \
            if self._window > 1 and self._pinv is not None else None
        self._solvers: dict = {}
        self._patterns: dict = {}  # a blade's present probes (bool row bytes) -> (list, count, solver)
        # the complete layout's covariance terms for every blade, (3, n_blades, n_eo)
        self._g_rows = None if gi is None else np.stack([np.repeat(gt[None, :], g.n_blades, axis=0)
                                                         for gt in self._ginv])
        self._nsv_next = 0  # first revolution (index) of the next NSV block
        self._nsv_run = 0  # consecutive detected blocks so far
        self._nsv_last = None  # the last block's scan
        self._finished = False
        #: Probe batches dropped: a TOA not within a revolution of its OPR pulse.
        self.refused_batches = 0
        self.result: ProcessingResult | None = None
        self.last_outputs: list[RevolutionOutput] = []

    # -- input ---------------------------------------------------------------------------
    def push(self, revolution: int, opr_s: float, toa_s: np.ndarray) -> list[RevolutionOutput]:
        """Add one revolution; return the per-revolution outputs now computable.

        Parameters
        ----------
        revolution : int
            Revolution number (consecutive; a gap is filled, a repeat or step back raises).
        opr_s : float
            The revolution's OPR time, s.
        toa_s : ndarray, shape (n_blades, n_probes)
            TOAs, s (NaN: missing).
        """
        if self._finished:
            raise RuntimeError("push after finish")
        toa = np.asarray(toa_s, dtype=float)
        if toa.shape != self._shape:
            raise ValueError(f"toa_s must have shape {self._shape}, got {toa.shape}")
        revolution = int(revolution)
        if self._first_rev is None:
            self._first_rev = revolution
        expected = self._first_rev + self._opr.n
        if revolution < expected:
            raise ValueError(f"revolution {revolution} pushed after revolution {expected - 1}")
        out: list[RevolutionOutput] = []
        if revolution > expected:  # lost revolutions: no arrivals, OPR times interpolated
            last = self._opr[self._opr.n - 1]
            gap = revolution - expected
            for k in range(1, gap + 1):
                self._opr.append(last + (float(opr_s) - last) * k / (gap + 1))
                self._toa.append(np.full(self._shape, np.nan))
                self._displace_ready(out)  # each one before the TOA history can move it to its file
        self._opr.append(float(opr_s))
        self._toa.append(toa)
        self._displace_ready(out)
        return out

    def _displace_ready(self, out: list) -> None:
        """Eq. 1 of every revolution whose next OPR pulse has come, and the outputs that
        completes (appended to ``out``). Revolution k needs OPR k+1 for its speed (and
        revolution 0 also OPR 2, for the acceleration of revolution 1)."""
        while self._n_done < self._opr.n - 1 and (self._n_done > 0 or self._opr.n >= 3):
            self._displace(self._n_done, final=False)
            self._n_done += 1
            out.extend(self._emit_ready(final=False))

    def advance(self, revolution: int, opr_s: float) -> list[RevolutionOutput]:
        """The OPR pulse of ``revolution``, ahead of its TOAs: the outputs it completes now.

        The previous revolution's speed needs only this pulse, so its displacements, fit and
        spectra need not wait for the new revolution's TOAs (a whole revolution later on real
        hardware). :meth:`push` of ``revolution`` follows as usual, with the same OPR time;
        the outputs are those :meth:`push` would have given. Nothing is done (``[]``) unless
        ``revolution`` is the next one; a step that would complete the calibration window
        waits for :meth:`push` (it needs the new TOAs).
        """
        if self._finished or self._first_rev is None or int(revolution) != self._first_rev + self._opr.n:
            return []
        out: list[RevolutionOutput] = []
        self._opr.append(float(opr_s))  # for this step only: push appends it with the TOAs
        try:
            while self._n_done < self._opr.n - 1 and (self._n_done > 0 or self._opr.n >= 3):
                if self._cal_window is not None and not self._calibrated and self._n_done + 1 >= self._cal_window[1]:
                    break  # completing the calibration window takes the new TOAs: push does it
                self._displace(self._n_done, final=False)
                self._n_done += 1
                out.extend(self._emit_ready(final=False))
        finally:
            self._opr.n -= 1
        return out

    def flush(self) -> list[RevolutionOutput]:
        """Outputs of the revolutions still pending at the end of the stream (the last
        revolution uses an extrapolated speed)."""
        out = []
        while self._opr.n >= 2 and self._n_done < self._opr.n:
            self._displace(self._n_done, final=self._n_done == self._opr.n - 1)
            self._n_done += 1
        out.extend(self._emit_ready(final=True))
        return out

    def finish(self, truth_peaks=None) -> dict:
        """Final resonance report over the whole history (the offline pipeline).

        Parameters
        ----------
        truth_peaks : TruthPeakTracker, Truth-like, TruthRows or TruthPeaks, optional
            Only for E_A and E_f (a tracker or per-revolution truth scores every crossing and
            dwell against its own window; peaks only, the crossings that contain them).

        Returns
        -------
        dict
            The brief's summary JSON dict; the :class:`ProcessingResult` is kept in
            :attr:`result` (without the whole run's spectra, ``probe_tw`` and ``fit_tw``:
            they went out with the live outputs). Outputs still pending when :meth:`flush` was not called are kept
            in :attr:`last_outputs`.
        """
        if not self._finished:
            self.last_outputs = self.flush()
            self._finished = True
            # the live displacements are done with: freed before the report's whole-run arrays
            self._d = self._omega = None
        if self._opr.n < 3:
            raise ValueError("at least three revolutions are needed for a resonance report")
        opts = self.options
        if opts.engine_orders is None and opts.eo_range is None:
            opts = replace(opts, engine_orders=engine_orders_of(self.info, opts))
        # the report only: the per-revolution spectra went out live, revolution by revolution
        toa = self._toa.scratch()  # the run's TOAs read back by blocks, never whole in memory
        try:
            self.result = process_arrays(self._opr.array, toa, self.info, opts, truth=truth_peaks,
                                         revolution0=self._first_rev or 0, spectra=False)
        finally:
            toa.close()
        return self.result.summary

    def nsv_ready(self) -> list[NsvDetection]:
        """Non-synchronous vibration of the blocks of revolutions completed since the last
        call (:mod:`.nsv`, ``options.nsv.block`` revolutions each): each detected block, once
        it is the ``min_blocks``-th consecutive one or later, as a one-block
        :class:`NsvDetection` (the final report groups the blocks over the whole run); not the
        rotor's own angular motion (:func:`~.nsv.is_rigid_body`).

        A block in which the calibration of the arrival angles switched on is skipped (its
        displacements change their zeroing mid-block)."""
        if self._d is None:  # after finish: the live displacements are gone
            return []
        opts = self.options.nsv
        L = int(opts.block)
        out = []
        while self._nsv_next + L <= self._n_done:
            s = self._nsv_next
            self._nsv_next += L
            cal = self._was_calibrated.rows(s, s + L)
            if cal.any() != cal.all():
                self._nsv_run, self._nsv_last = 0, None
                continue
            d = self._d.rows(s, s + L)
            finite = bool(np.isfinite(self._row_sum.rows(s, s + L)).all())  # a finite sum: finite samples
            if not screen_block(d, opts, finite=finite):  # the statistic alone first (most blocks stop here)
                self._nsv_run, self._nsv_last = 0, None
                continue
            scan = scan_blocks(d, self._omega.rows(s, s + L), self._psi, opts, starts=[0])
            if not scan.detected[0]:
                self._nsv_run, self._nsv_last = 0, None
                continue
            last = self._nsv_last
            same = last is not None and any(abs(scan.order[0] - o) <= 3.0 / L and scan.nd[0] == n for o, n in
                                            ((last.order[0], last.nd[0]), *last.alternatives[0]))
            self._nsv_run = self._nsv_run + 1 if same else 1
            self._nsv_last = scan
            if self._nsv_run >= int(opts.min_blocks):
                one = replace(opts, min_blocks=1)
                out += [det for det in detections(scan, d, self._psi, one, revolution0=(self._first_rev or 0) + s,
                                                  omega_rad_s=self._omega.rows(s, s + L))
                        if not is_rigid_body(det)]  # the rotor's own motion: the final report's note names it
        return out

    # -- per revolution -------------------------------------------------------------------
    def _displace(self, k: int, final: bool) -> None:
        """Eq. 1 of revolution ``k`` with the offline pipeline's rotor phase: the quadratic
        model through OPR pulses ``k-1, k, k+1`` (revolution 0 takes revolution 1's
        acceleration; the last one, at the end, an extrapolated speed), so that the streamed
        displacements are the offline ones."""
        opr = self._opr.array
        self._refuse_outside(k, opr)
        if self._cal_window is not None and not self._calibrated and k + 1 >= self._cal_window[1]:
            # the same arrival angles as offline: the window's phase model from its OPRs
            stop = self._cal_window[1]
            n_opr = min(stop + 1, self._opr.n)
            phase = rotor_phase_from_opr(opr[:n_opr])
            a = self._cal_window[0]
            b = max(min(stop, n_opr), a)  # the window's rows that the history holds
            psi = calibrate_arrival_angles(phase.rows(slice(a, b)), self._toa.rows(a, b), (0, b - a))
            self._psi = np.where(np.isfinite(psi), psi, self._psi)
            self._calibrated = True
        lo = max(0, k - 2) if final else max(0, k - 1)
        hi = k + 1 if final else max(k + 2, 3)
        keep = min(self._nsv_next, self._n_emitted - (self._window - 1) // 2)  # the oldest row still used
        for recent in (self._d, self._omega, self._row_sum, self._was_calibrated):
            recent.drop_before(keep)
        d = self._d.next_row()  # written in place
        om = revolution_displacements(opr[lo:hi], k - lo, self._toa.row(k), self._psi, self.geometry.tip_radius_m, d)
        self._row_sum.append(_add_all(d))
        self._omega.append(om)
        self._was_calibrated.append(self._calibrated or self._cal_window is None)

    def _refuse_outside(self, k: int, opr: np.ndarray) -> None:
        """Drop the probe batches of revolution ``k`` holding a TOA that is not within a
        revolution of its OPR pulse (:func:`~.displacement.outside_revolution`, the rule by
        which a recording holding one is refused): the batch's TOAs become missing (NaN) in
        the history, before Eq. 1, the calibration or the final report use them, and are
        counted in :attr:`refused_batches`. Revolution ``k``'s period needs OPR ``k + 1``
        (the last revolution takes the period before it)."""
        period = opr[k + 1] - opr[k] if k + 1 < opr.size else opr[k] - opr[k - 1]
        row = self._toa.row(k)
        # the rule's own arithmetic on the row's extremes first (NaN ignored; none finite: NaN,
        # both tests pass): only a row that may break it goes through the whole rule
        lo, hi = float(np.fmin.reduce(row, axis=None)) - opr[k], float(np.fmax.reduce(row, axis=None)) - opr[k]
        if not (lo < -period or hi > 2.0 * period or period <= 0.0):
            return
        bad = outside_revolution(row, opr[k], period).any(axis=0)
        if bad.any():
            row[:, bad] = np.nan
            self.refused_batches += int(np.count_nonzero(bad))

    def _solver(self, present: tuple):
        """Pseudo-inverse and covariance terms of ``B`` restricted to the present probes
        (cached per pattern of missing probes); None if they cannot separate the unknowns."""
        if present not in self._solvers:
            Bp = self._B[list(present)]
            npr, p = Bp.shape
            if npr < p or np.linalg.cond(Bp) > 1e10:
                self._solvers[present] = None
            else:
                gi = np.linalg.inv(Bp.T @ Bp)
                i1 = self._i1
                self._solvers[present] = (np.linalg.pinv(Bp).T, np.ascontiguousarray(Bp.T),
                                          (gi[i1, i1], gi[i1 + 1, i1 + 1], gi[i1, i1 + 1]), npr, p)
        return self._solvers[present]

    def _pattern(self, ok_b: np.ndarray) -> tuple:
        """``(present probes as a list, their count, solver)`` of a blade's pattern of present
        probes (a bool row), cached by the row's bytes."""
        key = ok_b.tobytes()
        got = self._patterns.get(key)
        if got is None:
            present = tuple(np.flatnonzero(ok_b).tolist())
            got = self._patterns[key] = (list(present), max(len(present), 1), self._solver(present))
        return got

    def _fit_patterns(self, d_k: np.ndarray):
        """Window-1 fits of one revolution with missing samples: complete blades through the
        shared pseudo-inverse, the others one by one (solvers cached per pattern)."""
        ok = ~np.isnan(d_k)
        full = ok.all(axis=1)
        x0 = np.where(ok, d_k, 0.0)
        a = x0 @ self._pinvT
        r = x0 - a @ self._BT
        rss = (r * r).sum(axis=1)
        s2 = rss * self._inv_dof
        n_used = np.full(d_k.shape[0], float(self._B.shape[0]))
        g = self._g_rows.copy()  # (3, n_blades, n_eo): the complete layout's terms, per blade
        for b in np.flatnonzero(~full).tolist():
            present, n_used[b], sol = self._pattern(ok[b])
            if sol is None:
                a[b], rss[b], s2[b] = np.nan, np.nan, np.nan
                continue
            pinvT, BT, gi, n, q = sol
            x = d_k[b, present]
            a[b] = x @ pinvT
            rb = x - a[b] @ BT
            rss[b] = rb @ rb
            s2[b] = rss[b] / (n - q) if n > q else np.nan
            g[0, b], g[1, b], g[2, b] = gi
        return a, rss, s2, g[0], g[1], g[2], n_used

    def _emit_ready(self, final: bool) -> list[RevolutionOutput]:
        out = []
        half_after = self._window // 2
        while self._n_emitted < self._n_done and (final or self._n_emitted + half_after < self._n_done):
            out.append(self._output(self._n_emitted))
            self._n_emitted += 1
        return out

    def _output(self, k: int) -> RevolutionOutput:
        d_k = self._d.row(k)
        w = self._window
        eo = self.engine_orders[0]
        om = float(self._omega.row(k))
        if w == 1 and self._pinv is not None:
            # the fit and both spectra as a few small matrix products (precomputed); the
            # element-wise steps run on contiguous (order, blade) rows (the same operations
            # on the same values as on the (blade, order) columns, fewer strided loops)
            missing = math.isnan(self._row_sum.row(k))  # np.isnan(d_k.sum())
            if missing:
                a, rss, s2, g11, g22, g12, n_used = self._fit_patterns(d_k)
                g11, g22, g12x2 = g11.T, g22.T, 2.0 * g12.T
                g1122 = _interleave(g11, g22)
            else:
                a = d_k @ self._pinvT  # (nb, p)
                r = d_k @ self._residual  # (I - B B^+) applied to each blade's samples
                rss = _add_rows(np.multiply(r, r, out=r), axis=1)
                s2 = rss * self._inv_dof
                g11, g22, g12x2 = self._ginv_col
                g1122 = self._g1122_col
                n_used = self._B.shape[0]
            # each operation with its operands in the original order (a NaN from both keeps
            # the first one's sign), in place where a temporary is not needed
            at = a.T.copy()  # (p, nb)
            a1, a2 = at[1::2], at[2::2]  # (n_eo, nb)
            sq = at[1:] * at[1:]  # a1 * a1, a2 * a2 interleaved
            amp2 = sq[0::2] + sq[1::2]
            ga = g1122 * at[1:]  # g11 * a1, g22 * a2 interleaved
            t = g12x2 * a2
            num = np.add(ga[0::2], t, out=t)
            num = np.multiply(a1, num, out=num)
            ga2 = ga[1::2]
            ga2 *= a2
            num += ga2  # a1 * (g11 * a1 + g12x2 * a2) + g22 * a2 * a2: (a1, a2) G (a1, a2)^T
            amp = np.sqrt(amp2)
            if not _all(amp2):  # no direction: the mean of the two variances
                zero = amp2 == 0
                num = np.where(zero, 0.5 * (g11 + g22), num)
                amp2 = np.where(zero, 1.0, amp2)
            amp = np.multiply(2.0, amp, out=amp)
            phase = np.arctan2(a2, a1)
            num = np.multiply(s2, num, out=num)
            num /= amp2
            amp_std = np.sqrt(num, out=num)
            amp_std = np.multiply(2.0, amp_std, out=amp_std)
            rss /= n_used
            dc, res = at[0], np.sqrt(rss, out=rss)
            if a1.shape[0] == 1:  # one EO: (1, nb) rows are (nb, 1) C-contiguous columns as they are
                amp_pkpk, phase, amp_std = amp.T, phase.T, amp_std.T
            else:
                amp_pkpk, phase, amp_std = _columns(amp), _columns(phase), _columns(amp_std)
            phasor = at[1] + 1j * at[2]
            nb = self.geometry.n_blades
            if missing:  # the conventions of probe_spectra / fit_spectra for NaN
                okd = ~np.isnan(d_k)
                cnt = okd.sum(axis=0)
                mean = np.where(cnt > 0, np.where(okd, d_k, 0.0).sum(axis=0) / np.maximum(cnt, 1), 0.0)
                X = np.abs(np.where(okd, d_k, mean).T @ self._F_probe)
                okp = ~np.isnan(phasor)
                n_ok = int(okp.sum())
                Q = np.abs(np.where(okp, phasor, 0.0) @ self._F_fit) * (nb / n_ok if n_ok else np.nan)
            else:
                X = np.abs(d_k.T @ self._F_probe)  # (n_probes, 2 n_nd)
                Q = np.abs(phasor @ self._F_fit)  # (2 n_nd,)
            n_nd = self._n_nd
            probe_tw = TravellingWaveSpectra(X[:, :n_nd], X[:, n_nd:], nb)
            fit_tw = TravellingWaveSpectra(Q[:n_nd], Q[n_nd:], nb)
        else:
            lo = max(0, k - (w - 1) // 2)
            hi = min(self._d.n, k + w // 2 + 1)
            if self._wfit is not None:  # fit_revolutions of the revolution's window, bit for bit
                f, i = self._wfit(self._d.rows(lo, hi)), 0
            else:
                f = fit_revolutions(self._d.rows(lo, hi), self.geometry.probe_angles_rad, self.engine_orders,
                                    window=w)
                i = k - lo
            amp_pkpk, phase, amp_std = f.amp_pkpk_m[i], f.phase_rad[i], f.amp_std_m[i]
            dc, res = f.dc_m[i], f.residual_rms_m[i]
            phasor = f.phasor[i, :, 0]
            probe_tw = probe_spectra(d_k, eo)
            fit_tw = fit_spectra(phasor, eo, self.geometry.blade_angles_rad)
        return RevolutionOutput(
            revolution=self._first_rev + k, opr_s=float(self._opr.row(k)), omega_rad_s=om,
            engine_orders=self.engine_orders, freq_hz=om * self._freq_per_omega, cn=self._cn,
            d_m=d_k.copy(), amp_pkpk_m=amp_pkpk, phase_rad=phase, amp_std_m=amp_std, dc_m=dc,
            residual_rms_m=res, probe_tw=probe_tw, fit_tw=fit_tw, calibrated=bool(self._was_calibrated.row(k)))


_add_rows = np.add.reduce  # ndarray.sum without its Python wrapper (the same reduction)


def _add_all(x: np.ndarray) -> float:
    """``float(x.sum())``: the same pairwise reduction, without ndarray.sum's Python wrapper."""
    return float(np.add.reduce(x, axis=None))


def _all(x: np.ndarray) -> bool:
    """``x.all()`` (NaN counts as true there too), by the faster ``count_nonzero``."""
    return np.count_nonzero(x) == x.size


def _interleave(g11: np.ndarray, g22: np.ndarray) -> np.ndarray:
    """Rows ``g11[0], g22[0], g11[1], ...`` of two (n_eo, m) arrays, shape (2 n_eo, m)."""
    out = np.empty((2 * g11.shape[0], g11.shape[1]))
    out[0::2], out[1::2] = g11, g22
    return out


def _columns(x: np.ndarray) -> np.ndarray:
    """(n_eo, n_blades) rows as C-contiguous (n_blades, n_eo) columns."""
    return np.ascontiguousarray(x.T)


def _spectrum_matrices(g: Geometry, eo: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The DFT columns of :func:`probe_spectra` and :func:`fit_spectra` as matrices, so that
    a complete revolution's spectra are two matrix products (forward then backward ND)."""
    nb = g.n_blades
    n_nd = nb // 2 + 1
    nd = np.arange(n_nd)
    b = np.arange(nb)
    scale = np.full(nb, 4.0 / nb)
    scale[0] = 2.0 / nb
    if nb % 2 == 0:
        scale[nb // 2] = 2.0 / nb
    bins_f, bins_b = (nd - eo) % nb, (-nd - eo) % nb
    F = np.exp(-2j * np.pi * np.outer(b, np.arange(nb)) / nb) * scale[None, :]
    F_probe = np.concatenate([F[:, bins_f], F[:, bins_b]], axis=1)
    rot = np.exp(1j * eo * g.blade_angles_rad)[:, None]
    G = rot * np.exp(-2j * np.pi * np.outer(b, np.arange(nb)) / nb) * (2.0 / nb)
    F_fit = np.concatenate([G[:, nd % nb], G[:, (-nd) % nb]], axis=1)
    return F_probe, F_fit, n_nd
