"""Variable-projection fits of many blades at once: ``y = C z(q) + c`` per blade, ``C`` and
``c`` complex and linear (solved exactly at every trial, Golub and Pereyra), ``q = (f_n,
zeta)`` by a bounded Levenberg-Marquardt iteration that advances every blade's problem
together (the methods of :mod:`.methods`: the quasi-steady shape, the swept SDOF model).

Each blade has its own samples: rows of ``(k, m)`` arrays with a mask ``w`` (``False`` past a
blade's last sample). With ``z_c = z - mean(z)`` over a blade's samples (orthogonal to the
constant column), the linear part is ``C = z_c^H y / |z_c|^2``, ``c = mean(y) - C mean(z)``,
and the residual ``r = C z + c - y``. A model derivative ``dz`` gives the Jacobian column
of the projected residual (variable projection, the Kaufman-free form)::

    dr = C P dz - (dz^H r / |z_c|^2) z_c,   P v = v - mean(v) - (z_c^H v / |z_c|^2) z_c

(``P`` the projector off ``[z, 1]``; the second term is ``A (A^H A)^-1 [dz^H r, 0]``). The
real problem stacks ``Re r`` and ``Im r``: ``J^T J = Re(dr^H dr)``, ``J^T r = Re(dr^H r)``.

The iteration (Marquardt with Nielsen's damping update, in the variables scaled by
``x_scale``): a step solves ``(J^T J + mu I) d = -J^T r`` for the parameters that are free
(a parameter on a bound that the gradient pushes outwards is held), goes along ``d`` as far
as the box allows (the bound it meets is then held exactly: an active set, never a step
clipped component by component into a corner), and is kept when it lowers the cost. A
blade stops when its free gradient is below ``gtol``, when a kept step lowers the cost by
less than ``ftol`` of it (with a ratio of actual to predicted reduction above 1/4), when
the step is shorter than ``xtol (xtol + |q|)`` (``scipy.optimize.least_squares``' tests
and tolerances), or after ``max_steps`` trials.

Pure numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LinearPart", "linear_part", "projected_jacobian", "VarProFit", "fit_blades", "inverse2", "pack_rows"]


@dataclass(frozen=True)
class LinearPart:
    """The linear part of ``y = C z + c`` per row, and what the projection needs."""

    C: np.ndarray  # (k,) complex
    c: np.ndarray  # (k,) complex
    r: np.ndarray  # (k, m) complex, C z + c - y; 0 off the mask
    zc: np.ndarray  # (k, m) complex, z minus its mean; 0 off the mask
    nz2: np.ndarray  # (k,) |z_c|^2: 1 / nz2 is (A^H A)^-1's [0, 0]
    n: np.ndarray  # (k,) samples

    @property
    def cost(self) -> np.ndarray:
        """``|r|^2 / 2`` per row (the real problem's cost)."""
        return 0.5 * np.sum(self.r.real ** 2 + self.r.imag ** 2, axis=1)


def linear_part(z: np.ndarray, y: np.ndarray, w: np.ndarray) -> LinearPart:
    """Least-squares ``(C, c)`` of ``y = C z + c`` over each row's samples ``w``.

    Parameters
    ----------
    z, y : ndarray of complex, shape (k, m)
    w : ndarray of bool, shape (k, m)
    """
    n = np.count_nonzero(w, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        zm = np.where(w, z, 0).sum(axis=1) / n
        ym = np.where(w, y, 0).sum(axis=1) / n
        zc = np.where(w, z - zm[:, None], 0)
        nz2 = np.sum(zc.real ** 2 + zc.imag ** 2, axis=1)
        C = np.sum(zc.conj() * np.where(w, y, 0), axis=1) / nz2
        c = ym - C * zm
        r = np.where(w, C[:, None] * z + c[:, None] - y, 0)
    return LinearPart(C, c, r, zc, nz2, n)


def projected_jacobian(lp: LinearPart, dz: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The residual's derivative with the linear part re-solved (module docstring), one column
    per parameter: ``dz`` of shape ``(k, m, p)`` -> ``(k, m, p)`` complex, 0 off the mask."""
    dz = np.where(w[..., None], dz, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = dz.sum(axis=1) / lp.n[:, None]  # (k, p)
        along = np.einsum("km,kmp->kp", lp.zc.conj(), dz) / lp.nz2[:, None]
        back = np.einsum("kmp,km->kp", dz.conj(), lp.r) / lp.nz2[:, None]
        zc = lp.zc[..., None]
        cols = lp.C[:, None, None] * (dz - mean[:, None, :] - along[:, None, :] * zc) - back[:, None, :] * zc
    return np.where(w[..., None], cols, 0)


def _normal(cols: np.ndarray, r: np.ndarray):
    """``J^T J`` (k, p, p) and ``J^T r`` (k, p) of the stacked real problem."""
    jtj = np.einsum("kmp,kmq->kpq", cols.conj(), cols).real
    jtr = np.einsum("kmp,km->kp", cols.conj(), r).real
    return jtj, jtr


@dataclass(frozen=True)
class VarProFit:
    """What :func:`fit_blades` found, per row."""

    q: np.ndarray  # (k, 2) the nonlinear parameters; NaN where the fit could not start
    jtj: np.ndarray  # (k, 2, 2) J^T J at q (the stacked real residual's)
    ok: np.ndarray  # (k,) bool: started (a feasible, finite start) and ended finite
    steps: np.ndarray  # (k,) trials
    extra: tuple = ()  # what the model returned beside the residual at q, per row (arrays of k rows)


def fit_blades(model, q0: np.ndarray, lower: np.ndarray, upper: np.ndarray, x_scale: np.ndarray, *,
               ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8, max_steps: int = 200) -> VarProFit:
    """Minimise each row's ``|C z(q) + c - y|^2`` over ``lower <= q <= upper``.

    Parameters
    ----------
    model : callable
        ``model(q, rows) -> (LinearPart, cols, extra)`` for the rows ``rows`` (int array) at
        ``q`` (shape ``(len(rows), 2)``): the linear part, :func:`projected_jacobian`'s
        columns, and a tuple of arrays with one row per fitted row (kept for the final ``q``:
        :attr:`VarProFit.extra`; ``()`` for none).
    q0, lower, upper, x_scale : ndarray, shape (k, 2)
        Start, bounds, and the typical scale of each parameter's change.

    Returns
    -------
    VarProFit
    """
    q0, lower, upper, x_scale = (np.array(a, dtype=float, copy=True) for a in (q0, lower, upper, x_scale))
    k = q0.shape[0]
    q = q0.copy()
    jtj = np.full((k, 2, 2), np.nan)
    steps = np.zeros(k, dtype=int)
    start = (np.all(np.isfinite(q0) & np.isfinite(x_scale) & (x_scale > 0), axis=1)
             & np.all((lower <= q0) & (q0 <= upper) & (lower < upper), axis=1))
    ok = start.copy()
    rows = np.flatnonzero(start)
    if rows.size:
        lp, cols, got = model(q[rows], rows)
        extra = tuple(np.zeros((k,) + a.shape[1:], a.dtype) for a in got)
        for e, a in zip(extra, got):
            e[rows] = a
        cost = lp.cost
        good = np.isfinite(cost) & np.all(np.isfinite(cols), axis=(1, 2))
        ok[rows[~good]] = False
        rows, cost, cols, r = rows[good], cost[good], cols[good], lp.r[good]
        del lp, got  # only the kept rows' columns and residuals (the model's memory bounded by its calls)
    else:
        cost, extra = np.zeros(0), ()
    if rows.size:
        a, g = _normal(cols, r)
        del cols, r
        jtj[rows] = a
        s = x_scale[rows]
        mu = 1e-3 * np.max(np.diagonal(a, axis1=1, axis2=2) * s * s, axis=1)
        mu = np.where(mu > 0, mu, 1e-3)
        nu = np.full(rows.size, 2.0)
        while rows.size:
            s = x_scale[rows]
            qr, lo, hi = q[rows], lower[rows], upper[rows]
            a_s = jtj[rows] * s[:, :, None] * s[:, None, :]
            g_s = g * s  # J^T r in the scaled variables
            # a parameter on a bound that the descent would push out of the box stays there
            blocked = ((qr <= lo) & (g_s > 0)) | ((qr >= hi) & (g_s < 0))
            small_g = np.max(np.abs(np.where(blocked, 0.0, g_s)), axis=1) < gtol
            if small_g.any():
                live = ~small_g
                rows, cost, mu, nu, g = rows[live], cost[live], mu[live], nu[live], g[live]
                s, qr, lo, hi, a_s, g_s, blocked = (v[live] for v in (s, qr, lo, hi, a_s, g_s, blocked))
                if not rows.size:
                    break
            free = ~blocked
            m = a_s * (free[:, :, None] & free[:, None, :]) + (mu[:, None] * free + blocked)[:, :, None] * np.eye(2)
            d = _solve2(m, -np.where(free, g_s, 0.0))
            # along the step, as far as the box allows; the bound it meets is held exactly
            with np.errstate(invalid="ignore", divide="ignore"):
                reach = np.where(d > 0, (hi - qr) / s / d, np.where(d < 0, (lo - qr) / s / d, np.inf))
            alpha = np.minimum(np.min(reach, axis=1), 1.0)
            q_try = np.clip(qr + alpha[:, None] * d * s, lo, hi)
            meets = (reach <= alpha[:, None]) & (alpha < 1.0)[:, None]
            q_try = np.where(meets & (d > 0), hi, np.where(meets & (d < 0), lo, q_try))
            d = (q_try - qr) / s  # the step taken, scaled
            steps[rows] += 1
            lp_try, cols_try, got = model(q_try, rows)
            cost_try = lp_try.cost
            pred = -(np.sum(g_s * d, axis=1) + 0.5 * np.einsum("kp,kpq,kq->k", d, a_s, d))
            finite = np.isfinite(cost_try) & np.all(np.isfinite(cols_try), axis=(1, 2))
            keep = finite & (cost_try < cost)
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                rho = np.where(pred > 0, (cost - cost_try) / pred, 0.0)
                shrink = np.maximum(1.0 / 3.0, 1.0 - (2.0 * np.clip(rho, -1.0, 2.0) - 1.0) ** 3)
            dnorm = np.sqrt(np.sum(d * d, axis=1))
            small_x = dnorm <= xtol * (xtol + np.sqrt(np.sum(qr ** 2, axis=1)))
            small_f = keep & (cost - cost_try < ftol * cost) & (rho > 0.25)
            # the kept trials move; the damping follows the gain ratio
            idx = rows[keep]
            q[idx] = q_try[keep]
            for e, a in zip(extra, got):
                e[idx] = a[keep]
            a_new, g_new = _normal(cols_try[keep], lp_try.r[keep])
            del lp_try, cols_try, got  # before the next trial's model
            jtj[idx] = a_new
            g = g.copy()
            g[keep] = g_new
            cost = np.where(keep, cost_try, cost)
            with np.errstate(over="ignore"):
                mu = np.where(keep, mu * shrink, mu * nu)
                nu = np.where(keep, 2.0, nu * 2.0)
            done = small_x | small_f | (steps[rows] >= max_steps) | ~np.isfinite(mu) | (mu > 1e300)
            live = ~done
            rows, cost, mu, nu, g = rows[live], cost[live], mu[live], nu[live], g[live]
    ok &= np.all(np.isfinite(q), axis=1)
    q[~start] = np.nan
    return VarProFit(q=q, jtj=jtj, ok=ok, steps=steps, extra=extra)


def _solve2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve the 2 x 2 systems ``a x = b`` (batched; symmetric positive definite ``a``)."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        x0 = (a[:, 1, 1] * b[:, 0] - a[:, 0, 1] * b[:, 1]) / det
        x1 = (a[:, 0, 0] * b[:, 1] - a[:, 1, 0] * b[:, 0]) / det
    return np.stack([x0, x1], axis=1)


def inverse2(a: np.ndarray) -> np.ndarray:
    """Inverse of each 2 x 2 matrix of ``a`` (k, 2, 2); NaN where singular or not finite."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    bad = ~(np.isfinite(det) & (det != 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.stack([np.stack([a[:, 1, 1], -a[:, 0, 1]], axis=1),
                        np.stack([-a[:, 1, 0], a[:, 0, 0]], axis=1)], axis=1) / det[:, None, None]
    inv[bad] = np.nan
    return inv


def pack_rows(w: np.ndarray, *arrays: np.ndarray) -> tuple:
    """Each row's samples where ``w`` moved to the row's start, in their order: ``(w, *arrays)``
    reordered alike (the rows' layout :func:`fit_blades`' models take)."""
    order = np.argsort(~w, axis=1, kind="stable")
    return tuple(np.take_along_axis(a, order, axis=1) for a in (w, *arrays))
