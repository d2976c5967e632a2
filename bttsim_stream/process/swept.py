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

import math

import numpy as np

__all__ = ["first_order", "sdof_envelope", "SweptForcing", "SWEPT_MEMORY"]

TWO_PI = 2.0 * np.pi

#: Envelopes and solves :class:`SweptForcing` remembers, the newest (a fit's last trials: each
#: one grid long, so the memory does not grow with the fit).
SWEPT_MEMORY = 3


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
    shift, n = 1, v.shape[1]
    while shift < n:
        v[:, shift:] += np.exp(lam_h * shift) * v[:, :-shift]  # the right side is evaluated first
        shift *= 2
    return v[:, 1:].reshape(x.shape)


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


def _poles(fn_hz: float, zeta: float):
    """``(lambda_1, lambda_2)`` and their derivatives by ``f_n`` and by ``zeta``."""
    wn = TWO_PI * fn_hz
    s = math.sqrt(max(1.0 - zeta * zeta, 1e-12))
    lam = (-zeta * wn + 1j * wn * s, -zeta * wn - 1j * wn * s)
    d_fn = (TWO_PI * (-zeta + 1j * s), TWO_PI * (-zeta - 1j * s))
    d_zeta = (wn * (-1.0 - 1j * zeta / s), wn * (-1.0 + 1j * zeta / s))
    return lam, d_fn, d_zeta


class SweptForcing:
    """The forcing's terms on one grid (they do not depend on ``f_n``, ``zeta``: computed once per
    crossing, not once per trial of the fit), and each blade's envelopes, derivatives and linear
    solves by ``(f_n, zeta)``: the fit's Jacobian, its swept peak and its last trial reuse them
    instead of integrating the same model again."""

    def __init__(self, grid_s: np.ndarray, phi_rad: np.ndarray):
        self.grid, self.phi = grid_s, phi_rad
        self.h = h = float(grid_s[1] - grid_s[0])
        self.w = w = np.diff(phi_rad) / h
        self.e_phi = np.exp(1j * phi_rad[:-1])
        self.e_wh = np.exp(1j * w * h)
        self.jw = 1j * w
        self.e_phi0 = np.exp(1j * phi_rad[0])
        self.e_mphi = np.exp(-1j * phi_rad)
        self._z: dict = {}
        self._dz: dict = {}
        self._y: dict = {}
        self._solved: dict = {}

    def _response(self, key):
        """Both poles' recursions at ``key = (f_n, zeta)``: ``(lam, x, den, y)``, ``y`` of shape
        ``(2, M + 1)`` (remembered until :meth:`clear`)."""
        got = self._y.get(key)
        if got is None:
            lam = np.array(_poles(*key)[0])[:, None]
            den = self.jw[None, :] - lam
            x = self.e_phi * (self.e_wh - np.exp(lam * self.h)) / den
            y = np.empty((2, x.shape[1] + 1), complex)
            y[:, 0] = self.e_phi0 / den[:, 0]
            y[:, 1:] = first_order(lam[:, 0] * self.h, x, y[:, 0])
            got = self._y[key] = (lam, x, den, y)
            _forget_oldest(self._y)
        return got

    def envelope(self, fn_hz: float, zeta: float) -> np.ndarray:
        """:func:`sdof_envelope` of ``(fn_hz, zeta)`` on this grid (remembered until :meth:`clear`)."""
        key = (float(fn_hz), float(zeta))
        z = self._z.get(key)
        if z is None:
            lam, _, _, y = self._response(key)
            z = self._z[key] = (y[0] - y[1]) / (lam[0, 0] - lam[1, 0]) * self.e_mphi
            _forget_oldest(self._z)
        return z

    def derivatives(self, fn_hz: float, zeta: float):
        """``(z, dz / d f_n, dz / d zeta)`` on this grid: ``dy / d lambda`` of each pole by the
        module docstring's recursion, through ``q = (y_1 - y_2) / (lambda_1 - lambda_2)``."""
        key = (float(fn_hz), float(zeta))
        got = self._dz.get(key)
        if got is None:
            lam, x, den, y = self._response(key)
            ah = np.exp(lam * self.h) * self.h
            u = ah * y[:, :-1] + (x - ah * self.e_phi) / den
            dy = np.empty_like(y)
            dy[:, 0] = y[:, 0] / den[:, 0]
            dy[:, 1:] = first_order(lam[:, 0] * self.h, u, dy[:, 0])
            d = lam[0, 0] - lam[1, 0]
            q = (y[0] - y[1]) / d
            dq1, dq2 = (dy[0] - q) / d, (q - dy[1]) / d  # dq / d lambda_1, dq / d lambda_2
            _, d_fn, d_zeta = _poles(*key)
            got = self._dz[key] = (self.envelope(*key), (dq1 * d_fn[0] + dq2 * d_fn[1]) * self.e_mphi,
                                   (dq1 * d_zeta[0] + dq2 * d_zeta[1]) * self.e_mphi)
            _forget_oldest(self._dz)
        return got

    def solve(self, q, ts: np.ndarray, yn: np.ndarray):
        """``(A, c, A c - yn)``: the linear part ``yn = C z(ts) + c`` of the SDOF fit at ``q = (f_n, zeta)``."""
        key = (float(q[0]), float(q[1]))
        got = self._solved.get(key)
        if got is None:
            z = interp_complex(ts, self.grid, self.envelope(q[0], q[1]))
            A = np.stack([z, np.ones_like(z)], axis=1)
            c, *_ = np.linalg.lstsq(A, yn, rcond=None)
            got = self._solved[key] = (A, c, A @ c - yn)
            _forget_oldest(self._solved)
        return got

    def jacobian(self, q, ts: np.ndarray, yn: np.ndarray) -> np.ndarray:
        """Jacobian of ``[Re r, Im r]``, ``r = A c - yn`` with ``c`` the linear least-squares
        solution (variable projection, Golub and Pereyra): ``dr = P dA c - A (A^H A)^-1 dA^H r``,
        ``P`` the projector off the columns of ``A``, ``dA`` the envelope's derivative in the
        first column. Shape ``(2 m, 2)``."""
        A, c, r = self.solve(q, ts, yn)
        _, dz_fn, dz_zeta = self.derivatives(q[0], q[1])
        Q, R = np.linalg.qr(A)
        cols = []
        for dz_grid in (dz_fn, dz_zeta):
            dz = interp_complex(ts, self.grid, dz_grid)
            v = c[0] * dz
            v = v - Q @ (Q.conj().T @ v)
            g = np.linalg.solve(R.conj().T, np.array([np.vdot(dz, r), 0.0]))  # R^-H dA^H r
            cols.append(v - Q @ g)
        d = np.stack(cols, axis=1)
        return np.concatenate([d.real, d.imag])

    def fit(self, ts: np.ndarray, yn: np.ndarray, fn0_hz: float, zeta0: float):
        """The nonlinear least-squares fit of ``(f_n, zeta)`` (``yn = C z(ts) + c`` with ``C``, ``c``
        solved linearly at each trial) from ``(fn0_hz, zeta0)``, within 20 % of ``fn0_hz`` and
        ``1e-5 <= zeta <= 0.3``, with :meth:`jacobian`: :func:`scipy.optimize.least_squares`'
        result."""
        from scipy.optimize import least_squares

        def resid(q):
            r = self.solve(q, ts, yn)[2]
            return np.concatenate([r.real, r.imag])

        return least_squares(resid, [fn0_hz, zeta0], jac=lambda q: self.jacobian(q, ts, yn),
                             x_scale=[max(fn0_hz * zeta0 * 0.1, 1e-3), zeta0 * 0.1],
                             bounds=([0.8 * fn0_hz, 1e-5], [1.2 * fn0_hz, 0.3]))

    def clear(self) -> None:
        """Forget the remembered envelopes and solves (the next blade's data differ)."""
        self._z.clear()
        self._dz.clear()
        self._y.clear()
        self._solved.clear()


def _forget_oldest(memory: dict) -> None:
    """Drop the oldest entries of ``memory`` beyond :data:`SWEPT_MEMORY`."""
    while len(memory) > SWEPT_MEMORY:
        del memory[next(iter(memory))]


def interp_complex(x, xp, fp):
    """:func:`numpy.interp` of a complex ``fp``."""
    return np.interp(x, xp, fp.real) + 1j * np.interp(x, xp, fp.imag)
