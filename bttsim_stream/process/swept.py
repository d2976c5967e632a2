"""The swept single-degree-of-freedom model of :func:`~.methods.sdof_method`: the envelope of a
unit-forced modal coordinate over a measured speed profile, its derivatives with respect to the
natural frequency and the damping ratio, and the Jacobian of the variable-projection fit.

``q'' + 2 zeta w_n q' + w_n^2 q = exp(i phi(t))`` (``phi = EO x`` rotor angle) is split into its
poles ``lambda_1,2 = -zeta w_n +- i w_d``, ``q = (y_1 - y_2) / (lambda_1 - lambda_2)``,
``y' = lambda y + exp(i phi)``. Over each step of a uniform grid the forcing phase is linear,
so each pole's recursion is exact::

    y_{m+1} = a y_m + x_m,   a = e^{lambda h},
    x_m = e^{i phi_m} (e^{i w_m h} - a) / (i w_m - lambda)

from the quasi-steady start ``y_0 = e^{i phi_0} / (i w_0 - lambda)``. Its derivative with
respect to ``lambda`` obeys the same recursion with the input
``h a y_m + (x_m - h a e^{i phi_m}) / (i w_m - lambda)`` from ``y_0 / (i w_0 - lambda)``.
The recursion is solved by a prefix scan (:func:`first_order`), vectorised over samples and
over both poles.

Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["first_order", "sdof_envelope", "SweptForcing", "UniformGrid", "ROW_SAMPLES", "SEGMENT_STEPS", "FIT_SAMPLES"]

TWO_PI = 2.0 * np.pi



def first_order(lam_h, x: np.ndarray, y0) -> np.ndarray:
    """``y_1 .. y_M`` of ``y_{m+1} = a y_m + x_m``, ``a = exp(lam_h)``, from ``y_0``; several
    recursions at once (one per row).

    A prefix scan by doubling (Hillis and Steele): over ``[y_0, x_0, .., x_{M-1}]``, step ``s``
    adds ``a^(2^s)`` times the value ``2^s`` samples back, so after ``ceil(log2(M + 1))`` steps
    each value is ``sum_k a^(n-k) v_k``. The powers are ``exp(2^s lam_h)``, not repeated
    products; for ``Re lam_h <= 0`` each is at most 1 in magnitude, so every step adds terms no
    larger than the values (the rounding grows as ``log2 M``, not as ``M``).

    Parameters
    ----------
    lam_h : complex or ndarray of complex, shape (p,)
        ``lambda h`` of each recursion.
    x : ndarray of complex, shape (M,) or (p, M)
    y0 : complex or ndarray of complex, shape (p,)

    Returns
    -------
    ndarray of complex, the shape of ``x``
    """
    x = np.asarray(x, dtype=complex)
    lam_h = np.asarray(lam_h, dtype=complex).reshape(-1, 1)
    v = np.empty((lam_h.size, x.shape[-1] + 1), complex)
    v[:, 0] = y0
    v[:, 1:] = x.reshape(lam_h.size, -1)
    _scan(_powers(lam_h, v.shape[1]), v, np.empty((lam_h.size, x.shape[-1]), complex))
    return v[:, 1:].reshape(x.shape)


def _powers(lam_h: np.ndarray, n: int) -> np.ndarray:
    """``exp(2^s lam_h)`` for each step ``s`` of :func:`_scan` over ``n`` values
    (``2^s < n``): shape ``(steps, p, 1)`` for ``lam_h`` of shape ``(p, 1)``."""
    shifts = [1 << s for s in range(max(n - 1, 0).bit_length())]
    return np.exp(lam_h[None] * np.array(shifts, dtype=float)[:, None, None])


def _scan(powers: np.ndarray, v: np.ndarray, tmp: np.ndarray) -> None:
    """:func:`first_order`'s doubling scan in place: each row ``[y_0, x_0, .., x_{M-1}]`` of
    ``v`` (shape ``(p, M + 1)``) becomes ``[y_0, y_1, .., y_M]``; ``powers`` from
    :func:`_powers` (at least ``M + 1`` values' steps); ``tmp`` of shape ``(p, >= M)`` holds
    each step's shifted terms (its contents are lost)."""
    shift, n, step = 1, v.shape[1], 0
    while shift < n:
        terms = np.multiply(powers[step], v[:, :-shift], out=tmp[:, :n - shift])
        np.add(v[:, shift:], terms, out=v[:, shift:])
        shift, step = 2 * shift, step + 1


def sdof_envelope(fn_hz: float, zeta: float, grid_s: np.ndarray, phi_rad: np.ndarray) -> np.ndarray:
    """Envelope ``z = q exp(-i phi)`` of the unit-forced modal coordinate on a uniform grid
    (the module docstring's recursion; the start is the quasi-steady state).

    Parameters
    ----------
    fn_hz, zeta : float
    grid_s : ndarray, shape (m,)
        Uniform time grid, s.
    phi_rad : ndarray, shape (m,)
        Forcing phase on the grid (``EO x`` rotor angle), rad.

    Returns
    -------
    ndarray of complex, shape (m,)
    """
    return SweptForcing(grid_s, phi_rad).envelope(fn_hz, zeta)


def _poles(fn_hz, zeta):
    """``(lambda_1, lambda_2)`` and their derivatives by ``f_n`` and by ``zeta``, each of shape
    ``(k, 2)`` for ``k`` pairs ``(f_n, zeta)``."""
    fn_hz, zeta = np.atleast_1d(np.asarray(fn_hz, dtype=float)), np.atleast_1d(np.asarray(zeta, dtype=float))
    wn = TWO_PI * fn_hz
    s = np.sqrt(np.maximum(1.0 - zeta * zeta, 1e-12))
    lam = np.stack([-zeta * wn + 1j * wn * s, -zeta * wn - 1j * wn * s], axis=1)
    d_fn = TWO_PI * np.stack([-zeta + 1j * s, -zeta - 1j * s], axis=1)
    d_zeta = wn[:, None] * np.stack([-1.0 - 1j * zeta / s, -1.0 + 1j * zeta / s], axis=1)
    return lam, d_fn, d_zeta


#: Rows (blades x poles) times grid samples that :class:`SweptForcing` integrates at once: a
#: block of 512 kB per complex array (it stays in a core's cache), whatever the crossing's length.
ROW_SAMPLES = 1 << 15

#: Grid steps integrated at once along the time axis: a longer crossing (a slower sweep) is
#: integrated in segments of this many steps, each starting from the previous one's last value,
#: so the model's memory does not grow with the crossing's length. A grid of at most this many
#: steps is one segment.
SEGMENT_STEPS = ROW_SAMPLES // 2

#: Blades times samples that :meth:`SweptForcing.fit` fits at once, and that
#: :func:`~.methods.sdof_method` prepares, fits and evaluates at once (the blades of a long
#: crossing in groups, at least one blade a group: each blade's fit is its own, so the groups
#: change no number). About 200 bytes a sample while fitted: with the integration's segments
#: (:data:`SEGMENT_STEPS`) the fit's memory, whatever the crossing's length (a blade's samples
#: are fitted together, however many: a reduction over a row is not split).
FIT_SAMPLES = 1 << 15


class UniformGrid:
    """The grid ``t0 + h j``, ``j = 0 .. size - 1``, s, computed at the indices asked for (the
    values of ``t0 + h * np.arange(size)``, with no array over the whole grid): ``grid[j]`` for
    an int or an int array ``j`` (a negative int counts from the end)."""

    def __init__(self, t0: float, h: float, size: int):
        self.t0, self.h, self.size = float(t0), float(h), int(size)

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, j):
        if isinstance(j, (int, np.integer)) and j < 0:
            j += self.size
        return self.t0 + self.h * np.asarray(j, dtype=np.intp)


class SweptForcing:
    """The forcing's terms on one grid (they do not depend on ``f_n``, ``zeta``: computed once per
    crossing), and, for many pairs ``(f_n, zeta)`` at once (one per blade), the envelopes,
    their derivatives and their values at each blade's sample times, integrated in blocks of
    :data:`ROW_SAMPLES` (rows) and :data:`SEGMENT_STEPS` (time); :meth:`at` forms the
    derivatives at the grid points next to the sample times only."""

    def __init__(self, grid_s, phi_rad):
        """``grid_s``: the uniform grid, s (an ndarray, or a :class:`UniformGrid` that computes
        its points where asked); ``phi_rad``: the forcing phase on it, rad (an ndarray, or a
        callable ``phi_rad(s, e)`` giving it at the grid points ``s .. e - 1``, so that no array
        over the whole grid is held). The forcing's terms are formed one segment at a time
        (:meth:`_terms`)."""
        self.grid, self.phi = grid_s, phi_rad
        self.size = len(grid_s)
        self.h = float(grid_s[1] - grid_s[0])
        self._phi = phi_rad if callable(phi_rad) else (lambda s, e: phi_rad[s:e])

    def _terms(self, s: int, e: int) -> "_Terms":
        """The forcing's terms of the segment of grid points ``s .. e`` (:class:`_Terms`): the
        same element-wise operations as over the whole grid, so each value is the same."""
        phi = self._phi(s, e + 1)
        w = np.diff(phi) / self.h
        return _Terms(e_phi=np.exp(1j * phi[:-1]), e_wh=np.exp(1j * w * self.h), jw=1j * w,
                      e_mphi=np.exp(-1j * phi))

    def _segments(self):
        """``(s, e)`` grid points of each segment (``e`` included: the next one's ``s``)."""
        n = self.size - 1
        return [(s, min(s + SEGMENT_STEPS, n)) for s in range(0, max(n, 1), SEGMENT_STEPS)]

    def _pairs(self, fn_hz: np.ndarray, zeta: np.ndarray) -> "_Pairs":
        """The terms of ``k`` pairs ``(f_n, zeta)`` that do not depend on time: their poles and
        the poles' derivatives (:func:`_poles`), the scan's powers of ``a = e^{lambda h}``
        (:func:`_powers`), ``a``, ``h a``,
        ``lambda_1 - lambda_2`` and the quasi-steady starts ``y_0`` and ``dy_0 / d lambda``."""
        lam, d_fn, d_zeta = _poles(fn_hz, zeta)
        flat = lam.reshape(-1, 1)  # rows b0 pole 1, b0 pole 2, b1 pole 1, ...
        ah = np.exp(flat * self.h)
        phi01 = self._phi(0, 2)
        den0 = (1j * (np.diff(phi01) / self.h))[None, :1] - flat  # i w_0 - lambda
        y_s = (np.exp(1j * phi01[0]) / den0)[:, 0]  # the quasi-steady start
        longest = max(e - s + 1 for s, e in self._segments())
        return _Pairs(flat=flat, powers=_powers(flat * self.h, longest), ah=ah, ahh=ah * self.h,
                      d=(lam[:, 0] - lam[:, 1])[:, None],
                      d_fn=d_fn, d_zeta=d_zeta, y_s=y_s, dy_s=y_s / den0[:, 0])

    def _block(self, p: "_Pairs", derivatives: bool):
        """For ``k`` pairs (:meth:`_pairs`), each segment's :meth:`_step` ``(z, dz)``, a
        generator over :meth:`_segments`, each segment from the previous one's last values."""
        y_s, dy_s = p.y_s, p.dy_s
        for s, e in self._segments():
            z, dz, y_s, dy_s = self._step(self._terms(s, e), p, y_s, dy_s, derivatives)
            yield z, dz

    @staticmethod
    def _step(t: "_Terms", p: "_Pairs", y_s: np.ndarray, dy_s: np.ndarray | None, derivatives: bool):
        """One segment (its terms ``t``, :meth:`_terms`) for ``k`` pairs (:meth:`_pairs`) from
        the starts ``y_s`` and ``dy_s`` (per pole, shape ``(2 k,)``): the envelopes ``z`` of
        shape ``(k, e - s + 1)``, (with ``derivatives``, else None) the segment's
        :class:`_Derivatives`, and the segment's last ``y`` and ``dy / d lambda`` (the next
        one's starts; None without ``derivatives``). Both poles' recursions and, for the
        derivatives, ``dy / d lambda`` by the module docstring's recursion, through
        ``q = (y_1 - y_2) / (lambda_1 - lambda_2)``."""
        r, n = p.flat.shape[0], t.jw.size
        den = np.subtract(t.jw, p.flat, out=np.empty((r, n), complex))
        y = np.empty((r, n + 1), complex)  # [y_s, x_s, .., x_{e-1}], then y by the scan
        y[:, 0] = y_s
        x = np.subtract(t.e_wh, p.ah, out=y[:, 1:])
        np.multiply(t.e_phi, x, out=x)
        np.divide(x, den, out=x)
        if derivatives:  # dy's input but its h a y term: (x - h a e^{i phi}) / (i w - lambda)
            u = np.multiply(p.ahh, t.e_phi, out=np.empty((r, n), complex))
            np.subtract(x, u, out=u)
            np.divide(u, den, out=u)
        _scan(p.powers, y, den)
        del den
        y_e = y[:, -1].copy()
        q = np.subtract(y[0::2], y[1::2], out=np.empty((r // 2, n + 1), complex))
        np.divide(q, p.d, out=q)
        z = q * t.e_mphi
        if not derivatives:
            return z, None, y_e, None
        dy = np.empty((r, n + 1), complex)
        dy[:, 0] = dy_s
        np.multiply(p.ahh, y[:, :-1], out=dy[:, 1:])
        del y
        np.add(dy[:, 1:], u, out=dy[:, 1:])
        _scan(p.powers, dy, u)
        del u
        return z, _Derivatives(q, dy, p, t.e_mphi), y_e, dy[:, -1].copy()

    def _whole(self, fn_hz: float, zeta: float, derivatives: bool):
        """One pair's envelope (and derivatives, shape ``(G, 2)``) on the whole grid, the
        segments joined."""
        zs, dzs = [], []
        for z, dz in self._block(self._pairs(np.array([fn_hz], float), np.array([zeta], float)), derivatives):
            cut = 1 if zs else 0  # a segment's first point: the previous one's last
            zs.append(z[0, cut:])
            if derivatives:
                d_fn, d_zeta = dz.at(np.arange(cut, z.shape[1])[None, :])
                dzs.append(np.stack([d_fn[0], d_zeta[0]], axis=-1))
        return np.concatenate(zs), (np.concatenate(dzs) if derivatives else None)

    def envelope(self, fn_hz: float, zeta: float) -> np.ndarray:
        """:func:`sdof_envelope` of ``(fn_hz, zeta)`` on this grid, shape ``(G,)``."""
        return self._whole(fn_hz, zeta, False)[0]

    def derivatives(self, fn_hz: float, zeta: float):
        """``(z, dz / d f_n, dz / d zeta)`` on this grid, each of shape ``(G,)``."""
        z, dz = self._whole(fn_hz, zeta, True)
        return z, dz[:, 0], dz[:, 1]

    def at(self, fn_hz: np.ndarray, zeta: np.ndarray, ts: np.ndarray, derivatives: bool = False):
        """Each pair's envelope at its row of sample times, and its peak on the grid.

        Parameters
        ----------
        fn_hz, zeta : ndarray, shape (k,)
        ts : ndarray, shape (k, m)
            Sample times within the grid, s (a blade's unused samples: any time on the grid).
        derivatives : bool
            Also the derivatives at ``ts``.

        Returns
        -------
        z_ts : ndarray of complex, shape (k, m)
        dz_ts : ndarray of complex, shape (k, m, 2), or None
            ``dz / d f_n`` and ``dz / d zeta`` at ``ts``.
        peak : ndarray of int, shape (k,)
            The grid index of ``max |z|`` (the first, where several are equal).
        z_peak : ndarray of complex, shape (k,)
            ``z`` there.
        """
        fn_hz, zeta = np.asarray(fn_hz, dtype=float), np.asarray(zeta, dtype=float)
        ts = np.asarray(ts, dtype=float)
        k, g = fn_hz.size, self.size
        i = np.clip(np.floor((ts - self.grid[0]) / self.h).astype(np.intp), 0, g - 2)
        t = np.clip((ts - self.grid[i]) / (self.grid[i + 1] - self.grid[i]), 0.0, 1.0)  # np.interp's ends
        z_ts = np.empty(ts.shape, complex)
        dz_ts = np.empty(ts.shape + (2,), complex) if derivatives else None
        peak = np.zeros(k, dtype=np.intp)
        z_peak = np.zeros(k, complex)
        top = np.full(k, -1.0)
        segments = self._segments()
        per = max(1, ROW_SAMPLES // (2 * min(g, SEGMENT_STEPS + 1)))
        pairs = self._pairs(fn_hz, zeta)
        y_s, dy_s = pairs.y_s.copy(), pairs.dy_s.copy()  # each pole's start of the next segment
        groups = [(a, min(k, a + per)) for a in range(0, k, per)]
        for s, e in segments:  # each segment's terms once, for every group of pairs
            terms = self._terms(s, e)
            last = e == g - 1
            for a, b in groups:
                pole = slice(2 * a, 2 * b)
                z, dz, y_e, dy_e = self._step(terms, pairs.rows(a, b), y_s[pole], dy_s[pole], derivatives)
                y_s[pole] = y_e
                if derivatives:
                    dy_s[pole] = dy_e
                rows = np.arange(b - a)
                ia, ta = i[a:b], t[a:b]
                mag = np.abs(z if last else z[:, :-1])  # the segment's own points (e: the next one's)
                j = np.argmax(mag, axis=1)
                mag_j = mag[rows, j]
                better = mag_j > top[a:b]  # the first maximum of the whole grid
                top[a:b] = np.where(better, mag_j, top[a:b])
                peak[a:b] = np.where(better, s + j, peak[a:b])
                z_peak[a:b] = np.where(better, z[rows, j], z_peak[a:b])
                inside = (ia >= s) & (ia < e) if len(segments) > 1 else None
                ic = np.clip(ia - s, 0, e - s - 1)  # the segment's interval of each sample
                flat_ic = ic + z.shape[1] * rows[:, None]  # the intervals' starts in z, flattened
                _lerp_into(z_ts[a:b], z.take(flat_ic), z.take(flat_ic + 1), ta, inside)
                if derivatives:  # at the samples' grid points only
                    m = ic.shape[1]
                    ends = dz.at(np.concatenate([ic, ic + 1], axis=1))
                    for c, dz_c in enumerate(ends):
                        _lerp_into(dz_ts[a:b, :, c], dz_c[:, :m], dz_c[:, m:], ta, inside)
                del z, dz, mag
        return z_ts, dz_ts, peak, z_peak

    def fit(self, ts: np.ndarray, yn: np.ndarray, w: np.ndarray, fn0_hz: np.ndarray, zeta0: float):
        """The variable-projection fit (:func:`.varpro.fit_blades`) of ``yn = C z(ts) + c`` per
        row, from ``(fn0_hz, zeta0)``, within 20 % of ``fn0_hz`` and ``1e-5 <= zeta <= 0.3``;
        its ``extra`` is :meth:`at`'s ``(z_ts, peak, z_peak)`` at the fitted point.

        Parameters
        ----------
        ts, yn : ndarray, shape (k, m)
            Each blade's sample times (s) and normalised responses.
        w : ndarray of bool, shape (k, m)
            Each blade's samples.
        fn0_hz : ndarray, shape (k,)
        zeta0 : float
        """
        from .varpro import VarProFit, fit_blades, linear_part, projected_jacobian

        def model(q, rows):
            z, dz, peak, z_peak = self.at(q[:, 0], q[:, 1], ts[rows], derivatives=True)
            lp = linear_part(z, yn[rows], w[rows])
            return lp, projected_jacobian(lp, dz, w[rows]), (z, peak, z_peak)

        fn0 = np.asarray(fn0_hz, dtype=float)
        ones = np.ones_like(fn0)
        q0 = np.stack([fn0, zeta0 * ones], axis=1)
        bounds = (np.stack([0.8 * fn0, 1e-5 * ones], axis=1), np.stack([1.2 * fn0, 0.3 * ones], axis=1))
        scale = np.stack([np.maximum(fn0 * zeta0 * 0.1, 1e-3), zeta0 * 0.1 * ones], axis=1)
        # each row is fitted on its own: a long crossing's blades in groups of FIT_SAMPLES samples
        per = max(1, FIT_SAMPLES // max(ts.shape[1], 1))
        if fn0.size <= per:
            return fit_blades(model, q0, *bounds, scale)
        parts = []
        for a in range(0, fn0.size, per):
            sl = slice(a, a + per)
            offset = a

            def part(q, rows, offset=offset):
                return model(q, rows + offset)

            parts.append(fit_blades(part, q0[sl], bounds[0][sl], bounds[1][sl], scale[sl]))
        shapes = next((f.extra for f in parts if f.extra), ())  # a group where no row started has none
        extra = tuple(np.concatenate([f.extra[j] if f.extra else np.zeros((f.q.shape[0],) + e.shape[1:], e.dtype)
                                      for f in parts]) for j, e in enumerate(shapes))
        return VarProFit(q=np.concatenate([f.q for f in parts]), jtj=np.concatenate([f.jtj for f in parts]),
                         ok=np.concatenate([f.ok for f in parts]), steps=np.concatenate([f.steps for f in parts]),
                         extra=extra)


@dataclass(frozen=True)
class _Terms:
    """:meth:`SweptForcing._terms` of one segment of grid points ``s .. e``: ``e_phi`` (``e^{i
    phi_m}``), ``e_wh`` (``e^{i w_m h}``), ``jw`` (``i w_m``), each of shape ``(e - s,)``, and
    ``e_mphi`` (``e^{-i phi}``, shape ``(e - s + 1,)``)."""

    e_phi: np.ndarray
    e_wh: np.ndarray
    jw: np.ndarray
    e_mphi: np.ndarray


@dataclass(frozen=True)
class _Pairs:
    """:meth:`SweptForcing._pairs`' terms of ``k`` pairs: per pole (``2 k`` rows, the pairs'
    two poles interleaved) ``flat`` (the poles, shape ``(2 k, 1)``), ``powers`` (``(steps, 2 k,
    1)``), ``ah``, ``ahh`` (``h a``) and the starts ``y_s``, ``dy_s``; per pair ``d``
    (``lambda_1 - lambda_2``, shape ``(k, 1)``), ``d_fn`` and ``d_zeta`` (``(k, 2)``)."""

    flat: np.ndarray
    powers: np.ndarray
    ah: np.ndarray
    ahh: np.ndarray
    d: np.ndarray
    d_fn: np.ndarray
    d_zeta: np.ndarray
    y_s: np.ndarray
    dy_s: np.ndarray

    def rows(self, a: int, b: int) -> "_Pairs":
        """The pairs ``a`` to ``b - 1``."""
        pole, pair = slice(2 * a, 2 * b), slice(a, b)
        return _Pairs(self.flat[pole], self.powers[:, pole], self.ah[pole], self.ahh[pole], self.d[pair],
                      self.d_fn[pair], self.d_zeta[pair], self.y_s[pole], self.dy_s[pole])


class _Derivatives:
    """``dz / d f_n`` and ``dz / d zeta`` of one segment of :meth:`SweptForcing._block`, from
    ``q`` (shape ``(k, L)``), ``dy / d lambda`` (``(2 k, L)``, the poles' rows interleaved)
    and the pairs' terms (:class:`_Pairs`), at the points asked for only:
    ``dq / d lambda_1 = (dy_1 - q) / d``, ``dq / d lambda_2 = (q - dy_2) / d``, then through
    the poles' derivatives, times ``exp(-i phi)``."""

    def __init__(self, q: np.ndarray, dy: np.ndarray, pairs: _Pairs, e_mphi: np.ndarray):
        self.q, self.dy, self.pairs, self.e_mphi = q, dy, pairs, e_mphi

    def at(self, j: np.ndarray):
        """``(dz / d f_n, dz / d zeta)`` at the segment's columns ``j`` (shape ``(k, n)``), each
        of shape ``(k, n)``."""
        n, p = self.q.shape[1], self.pairs
        row = n * np.arange(j.shape[0])[:, None]
        q = self.q.take(j + row)  # q, dy flattened: row b of q, rows 2 b (pole 1), 2 b + 1 of dy
        dq1 = (self.dy.take(j + 2 * row) - q) / p.d  # dq / d lambda_1
        dq2 = (q - self.dy.take(j + 2 * row + n)) / p.d  # dq / d lambda_2
        e_mphi = self.e_mphi[j]
        return ((dq1 * p.d_fn[:, :1] + dq2 * p.d_fn[:, 1:]) * e_mphi,
                (dq1 * p.d_zeta[:, :1] + dq2 * p.d_zeta[:, 1:]) * e_mphi)


def _lerp_into(out: np.ndarray, z0: np.ndarray, z1: np.ndarray, t: np.ndarray, inside: np.ndarray | None) -> None:
    """``out = z0 + t (z1 - z0)`` (each sample between its interval's ends ``z0``, ``z1``),
    where ``inside`` (None: everywhere; elsewhere left as it is)."""
    if inside is None:
        out[...] = z0 + t * (z1 - z0)
        return
    np.copyto(out, z0 + t * (z1 - z0), where=inside)
