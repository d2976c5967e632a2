"""Travelling-wave (nodal diameter) spectra: spatial DFT across the blades (paper Fig. 10).

Sign convention
---------------
Blades are numbered ``b = 0 .. N_b - 1`` in the direction of rotation (anticlockwise,
blade ``b`` near ``2 pi b / N_b``). A response whose phase advances by ``+2 pi k / N_b``
from one blade to the next,

``u_b(t) = A sin(EO phi(t) + 2 pi b k / N_b + c)``,

has **signed nodal diameter** ``+k`` and is reported as a **forward** wave of ND ``k``;
``-k`` is **backward**. This is exactly the phasing of the excitation, Eq. 7
(``2 pi (b-1) N_ND / N_b`` with the paper's 1-based ``b``), so a scenario with
``nodal_diameter = k`` (``0 < k <= N_b / 2``) is identified as forward ND ``k``, and
``nodal_diameter = N_b - k`` as backward ND ``k``. The pattern of an engine-order stimulus
fixed in the casing, ``sin(EO (phi + theta_b))``, is forward with ND ``EO`` (mod
``N_b``). Physically, in the rotor frame the crests of a forward wave move from blade
``b`` to blade ``b - 1``, i.e. against the rotation.

Two spectra
-----------
* :func:`probe_spectra` -- per revolution and probe, the DFT across the blades of that
  probe's displacements (the paper's Fig. 10). The probe sees blade ``b`` at rotor angle
  ``theta_j - theta_b``, so a wave of ND ``k`` appears in DFT bin ``(k - EO) mod N_b``; the
  bins are mapped back to signed ND with the known EO. One probe samples one real number
  per blade, so a wave and its image ``2 EO - k`` (mod ``N_b``, signed) have equal
  magnitude: ND 1 at EO 8 also shows backward ND 14, and ND 14 shows forward ND 2. The
  ND ``EO`` lands in the DC bin, which also holds any static offset common to the blades.
* :func:`fit_spectra` -- per revolution, the DFT across the blades of the complex response
  of the sine fit (all probes together), rotated into the rotor frame by ``EO theta_b``.
  The probes resolve the direction, so there is no image: this is what
  :func:`identify_nd` uses.

Magnitudes are peak-to-peak amplitudes of the wave component, m (a pure wave of
pk-pk amplitude ``2A`` on every blade gives ``2A`` at its ND). Arrays are
``(..., n_nd)`` with ``n_nd = floor(N_b / 2) + 1`` (ND 0..floor(N_b/2)); ND 0 (and
``N_b / 2`` for an even count) is a standing pattern and appears in both directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["TravellingWaveSpectra", "ProbeWave", "probe_spectra", "fit_spectra", "identify_nd", "signed_nd"]

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, slots=True, eq=False)
class TravellingWaveSpectra:
    """Forward and backward magnitudes by nodal diameter.

    Attributes
    ----------
    forward_m, backward_m : ndarray, shape (..., n_nd)
        Peak-to-peak magnitudes, m, for ND 0..n_nd-1.
    n_blades : int
    """

    forward_m: np.ndarray
    backward_m: np.ndarray
    n_blades: int

    @property
    def n_nd(self) -> int:
        return int(self.forward_m.shape[-1])

    @property
    def dominant_nd(self) -> np.ndarray:
        """Signed ND of the largest component (forward wins ties), shape (...)."""
        f, b = self.forward_m, self.backward_m
        if f.ndim == 1 and math.isfinite(np.add.reduce(f) + np.add.reduce(b)):
            # one spectrum (a revolution's), every value finite (a finite sum): what nan_to_num
            # would leave as it is, without its cost
            i_f, i_b = int(np.argmax(f)), int(np.argmax(b))
            return np.asarray(-i_b if b[i_b] > f[i_f] else i_f)
        f = np.nan_to_num(self.forward_m, nan=-np.inf)
        b = np.nan_to_num(self.backward_m, nan=-np.inf)
        i_f, i_b = np.argmax(f, axis=-1), np.argmax(b, axis=-1)
        vf = np.take_along_axis(f, i_f[..., None], -1)[..., 0]
        vb = np.take_along_axis(b, i_b[..., None], -1)[..., 0]
        return np.where(vb > vf, -i_b, i_f)


@dataclass(frozen=True, slots=True, eq=False)
class ProbeWave:
    """One probe's travelling-wave spectrum of one revolution, as the processor publishes it
    (``bttsim.v1.TravellingWave``).

    Attributes
    ----------
    probe : int
    forward_m, backward_m : ndarray, shape (n_nd,)
        Forward and backward magnitudes by nodal diameter 0..n_nd-1, m.
    nd : int
        The revolution's nodal diameter (signed: negative for a backward wave), identified
        from the fits of every probe.
    """

    probe: int
    forward_m: np.ndarray
    backward_m: np.ndarray
    nd: int

    @property
    def n_nd(self) -> int:
        return int(self.forward_m.size)

    def signed_spectrum(self) -> np.ndarray:
        """Magnitudes by signed ND, rows ``+(n_nd-1) .. 0 .. -(n_nd-1)`` (forward positive),
        shape (2 n_nd - 1,); ND 0 is the larger of its two estimates."""
        zero = np.fmax(self.forward_m[:1], self.backward_m[:1])
        return np.concatenate([self.forward_m[:0:-1], zero, self.backward_m[1:]])


def signed_nd(bin_index, n_blades: int):
    """Signed ND of a DFT bin ``k``: ``k`` for ``k <= N/2``, ``k - N`` above."""
    k = np.mod(bin_index, n_blades)
    return np.where(k <= n_blades // 2, k, k - n_blades)


def _split(Z: np.ndarray, n_blades: int, shift: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Forward/backward arrays from complex amplitudes per bin (last axis), signed ND
    ``k`` sitting in bin ``(k + shift) mod N``."""
    i_f, i_b = _split_bins(n_blades, shift)
    return np.abs(Z[..., i_f]), np.abs(Z[..., i_b])


@lru_cache(maxsize=64)
def _split_bins(n_blades: int, shift: int) -> tuple[np.ndarray, np.ndarray]:
    """The bins of signed ND ``+k`` and ``-k``, ``k = 0 .. N/2`` (:func:`_split`; computed
    once per blade count and shift)."""
    nd = np.arange(n_blades // 2 + 1)
    return _frozen((nd + shift) % n_blades), _frozen((-nd + shift) % n_blades)


@lru_cache(maxsize=64)
def _probe_scale(n_blades: int) -> np.ndarray:
    """pk-pk per DFT magnitude of a real sequence: ``4 / N``, but ``2 / N`` for the
    self-conjugate bins (0 and N/2), which hold a wave whole (computed once per blade count)."""
    scale = np.full(n_blades, 4.0 / n_blades)
    scale[0] = 2.0 / n_blades
    if n_blades % 2 == 0:
        scale[n_blades // 2] = 2.0 / n_blades
    return _frozen(scale)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


#: Revolutions transformed at once by :func:`probe_spectra`.
SPECTRA_CHUNK = 2048


def probe_spectra(d_m: np.ndarray, engine_order: int) -> TravellingWaveSpectra:
    """Per revolution and probe: spatial DFT of the displacements across the blades.

    Parameters
    ----------
    d_m : ndarray, shape (n_rev, n_blades, n_probes) or (n_blades, n_probes)
        Displacements, m; a missing blade takes the mean of the others at that probe.
    engine_order : int
        The EO used to map DFT bins to nodal diameters (bin ``(ND - EO) mod N_b``).

    Returns
    -------
    TravellingWaveSpectra
        Shape ``(n_rev, n_probes, n_nd)`` (or ``(n_probes, n_nd)``).
    """
    d = np.asarray(d_m, dtype=float)
    nb = d.shape[-2]
    if d.ndim == 3 and d.shape[0] > SPECTRA_CHUNK:  # per revolution: in blocks, bounded temporaries
        n_nd = nb // 2 + 1
        fwd, bwd = np.empty((d.shape[0], d.shape[2], n_nd)), np.empty((d.shape[0], d.shape[2], n_nd))
        for a in range(0, d.shape[0], SPECTRA_CHUNK):
            s = probe_spectra(d[a:a + SPECTRA_CHUNK], engine_order)
            fwd[a:a + SPECTRA_CHUNK], bwd[a:a + SPECTRA_CHUNK] = s.forward_m, s.backward_m
        return TravellingWaveSpectra(forward_m=fwd, backward_m=bwd, n_blades=nb)
    with np.errstate(all="ignore"):
        ok = np.isfinite(d)
        cnt = ok.sum(axis=-2, keepdims=True)
        mean = np.where(cnt > 0, np.where(ok, d, 0.0).sum(axis=-2, keepdims=True) / np.maximum(cnt, 1), 0.0)
    x = np.where(ok, d, mean)
    X = np.fft.fft(np.moveaxis(x, -2, -1), axis=-1)  # (..., n_probes, n_blades)
    # a real sequence splits a wave between bin m and N - m: pk-pk = 4 |X_m| / N, except
    # the self-conjugate bins (0 and N/2) which hold it whole
    X = X * _probe_scale(nb)
    fwd, bwd = _split(X, nb, shift=-int(engine_order))
    return TravellingWaveSpectra(forward_m=fwd, backward_m=bwd, n_blades=nb)


def fit_spectra(phasor: np.ndarray, engine_order: int, blade_angles_rad=None) -> TravellingWaveSpectra:
    """Per revolution: spatial DFT of the sine-fit responses across the blades.

    Parameters
    ----------
    phasor : ndarray, shape (n_rev, n_blades) or (n_blades,), complex
        ``a1 + i a2`` of one engine order (:attr:`SineFit.phasor`), m; NaN: missing.
    engine_order : int
    blade_angles_rad : ndarray, shape (n_blades,), optional
        Blade angles in the rotor frame (default ``2 pi b / N_b``); the response is
        rotated by ``exp(i EO theta_b)`` into the rotor frame before the DFT.

    Returns
    -------
    TravellingWaveSpectra
        Shape ``(n_rev, n_nd)`` (or ``(n_nd,)``).
    """
    p = np.asarray(phasor)
    nb = p.shape[-1]
    if p.ndim == 2 and p.shape[0] > SPECTRA_CHUNK:  # per revolution: in blocks, bounded temporaries
        n_nd = nb // 2 + 1
        fwd, bwd = np.empty((p.shape[0], n_nd)), np.empty((p.shape[0], n_nd))
        for a in range(0, p.shape[0], SPECTRA_CHUNK):
            s = fit_spectra(p[a:a + SPECTRA_CHUNK], engine_order, blade_angles_rad)
            fwd[a:a + SPECTRA_CHUNK], bwd[a:a + SPECTRA_CHUNK] = s.forward_m, s.backward_m
        return TravellingWaveSpectra(forward_m=fwd, backward_m=bwd, n_blades=nb)
    th = TWO_PI * np.arange(nb) / nb if blade_angles_rad is None else np.asarray(blade_angles_rad, float)
    ok = np.isfinite(p)
    n_ok = ok.sum(axis=-1, keepdims=True)
    q = np.where(ok, p, 0.0) * np.exp(1j * int(engine_order) * th)
    with np.errstate(all="ignore"):
        Q = np.fft.fft(q, axis=-1) * np.where(n_ok > 0, 2.0 / n_ok, np.nan)
    fwd, bwd = _split(Q, nb)
    return TravellingWaveSpectra(forward_m=fwd, backward_m=bwd, n_blades=nb)


def identify_nd(spectra: TravellingWaveSpectra, revolutions=None) -> int:
    """The signed ND with the most energy over the given revolutions.

    Parameters
    ----------
    spectra : TravellingWaveSpectra
        Shape ``(n_rev, n_nd)`` (e.g. from :func:`fit_spectra`).
    revolutions : index, optional
        Revolutions to sum over (e.g. the resonance); default all.

    Returns
    -------
    int
        Positive: forward; negative: backward (forward wins ties; ND 0 is 0).
    """
    f = spectra.forward_m if revolutions is None else spectra.forward_m[revolutions]
    b = spectra.backward_m if revolutions is None else spectra.backward_m[revolutions]
    ef = np.nansum(np.reshape(f, (-1, spectra.n_nd)) ** 2, axis=0)
    eb = np.nansum(np.reshape(b, (-1, spectra.n_nd)) ** 2, axis=0)
    i_f, i_b = int(np.argmax(ef)), int(np.argmax(eb))
    return -i_b if eb[i_b] > ef[i_f] else i_f
