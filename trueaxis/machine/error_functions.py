"""Component errors as functions of their axis' position: tables, Legendre series, Fourier series.

Every form is linear in its parameters (table values, series coefficients), so each can give its *basis*:
``basis(q) @ values == value(q)``. The basis is what makes the twin's parameter Jacobian exact and cheap, and what the
identifier solves for. Positions ``q`` are in internal units (mm for linear axes, rad for rotary axes); values are in
the machine file's units (um or urad).

``__call__`` and ``derivative`` are the reference evaluation (numpy and scipy, one function at a time).
``value_and_derivative`` gives the same numbers in one compiled pass; the twin packs all its functions together the
same way (``error_kernel.CompiledErrors``, from each function's ``compiled_form``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre as npleg

from . import error_kernel

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class ErrorFunction:
    """One component error (e.g. EXX) of one axis, linear in ``values``.

    kind : "linear" | "cubic" (tables over ``at``), "legendre" (series over ``domain`` mapped to [-1, 1]),
           "fourier" (series in the rotary angle: ``harmonics`` k per revolution, values [a1, b1, a2, b2, ...] for
           a_k cos(k q) + b_k sin(k q)).
    at : (n,) table positions in internal units (tables only).
    values : (n,) float, um or urad.
    periodic : table repeats every 2 pi (rotary tables spanning exactly 360 deg).
    """

    kind: str
    values: np.ndarray
    at: np.ndarray | None = None
    domain: tuple[float, float] | None = None
    harmonics: np.ndarray | None = None
    periodic: bool = False
    labels: tuple[str, ...] = field(default=())

    # --- evaluation -------------------------------------------------------------------------------------------
    def __call__(self, q: np.ndarray) -> np.ndarray:
        """Value at positions q (N,): (N,) in um or urad."""
        q = np.asarray(q, dtype=float)
        if self.kind == "linear":
            # A periodic table's last node is its first one a turn later: it carries the first value (as in basis).
            return np.interp(self._wrap(q), self.at, self._folded_values())
        if self.kind == "cubic":
            # The spline of the values themselves (the unit splines' coefficients contracted with the values): the
            # same function as basis(q) @ values without the (N, n) basis.
            return self._value_spline()(np.clip(self._wrap(q), self.at[0], self.at[-1]))
        if self.kind == "legendre":
            lo, hi = self.domain
            return npleg.legval(np.clip((2.0 * q - (lo + hi)) / (hi - lo), -1.0, 1.0), self.values)
        return self.basis(q) @ self.values

    def derivative(self, q: np.ndarray) -> np.ndarray:
        """d value / d q at q (N,): um per mm, or urad per rad, ..."""
        q = np.asarray(q, dtype=float)
        if self.kind == "linear":
            at, v = self.at, self._folded_values()
            x = self._wrap(q)
            inside = (x >= at[0]) & (x <= at[-1])
            i = np.clip(np.searchsorted(at, np.clip(x, at[0], at[-1]), side="right") - 1, 0, at.size - 2)
            return np.where(inside, (v[i + 1] - v[i]) / (at[i + 1] - at[i]), 0.0)
        if self.kind == "cubic":
            x = self._wrap(q)
            inside = (x >= self.at[0]) & (x <= self.at[-1])
            return self._value_spline().derivative()(np.clip(x, self.at[0], self.at[-1])) * inside
        if self.kind == "legendre":
            lo, hi = self.domain
            u = (2.0 * q - (lo + hi)) / (hi - lo)
            d = npleg.legval(np.clip(u, -1.0, 1.0), npleg.legder(self.values)) if self.values.size > 1 else 0.0 * u
            return d * (2.0 / (hi - lo)) * (np.abs(u) <= 1.0)
        return self.basis_derivative(q) @ self.values

    def value_and_derivative(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Value and d value / d q at q in one compiled pass: the numbers of ``__call__`` and ``derivative`` (to
        round-off, a few ulps), the table search, Fourier basis or Legendre mapping shared by both."""
        q = np.asarray(q, dtype=float)
        packed = self.__dict__.get("_compiled_cache")
        if packed is None:
            packed = error_kernel.CompiledErrors([(self, 0, 0, 0, 1.0)], (1, 1))
            object.__setattr__(self, "_compiled_cache", packed)
        v, dv = packed.evaluate(q.reshape(-1, 1), derivative=True)
        return v.reshape(q.shape), dv.reshape(q.shape)

    def compiled_form(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """(kind code, grid, coefficients, derivative coefficients): the plain arrays ``error_kernel`` evaluates
        (cached; see its group functions for the layouts).

        linear : grid = table positions; node values (periodic: the last carrying the first), then the interval slopes.
        cubic : grid = table positions; the value spline's PPoly coefficients (n - 1, 4), then its derivative's
                (n - 1, 3).
        legendre : grid = the domain (lo, hi); the series, then its derivative series (empty for a constant).
        fourier : grid = the harmonics; [a1, b1, a2, b2, ...], no derivative coefficients (they come from the basis).
        """
        form = self.__dict__.get("_form_cache")
        if form is not None:
            return form
        empty = np.empty(0)
        if self.kind == "linear":
            at, v = self.at, self._folded_values()
            # The slopes as np.interp computes them.
            form = (error_kernel.LINEAR, at, v, (v[1:] - v[:-1]) / (at[1:] - at[:-1]))
        elif self.kind == "cubic":
            # the value spline's PPoly coefficients and its derivative's (PPoly.derivative: c[:-1] times 3, 2, 1),
            # without scipy when the unit spline is in the disk cache (the post's start-up)
            c = np.tensordot(_unit_coefficients(self.at, self.periodic), self._folded_values(), axes=([2], [0]))
            dc = c[:-1] * np.array([3.0, 2.0, 1.0])[:, None]
            form = (error_kernel.CUBIC, self.at, c.T.ravel(), dc.T.ravel())
        elif self.kind == "legendre":
            d = npleg.legder(self.values) if self.values.size > 1 else empty
            form = (error_kernel.LEGENDRE, np.asarray(self.domain, dtype=float), self.values, d)
        elif self.kind == "fourier":
            form = (error_kernel.FOURIER, np.asarray(self.harmonics, dtype=float), self.values, empty)
        else:
            raise ValueError(f"unknown error-function kind {self.kind!r}")
        form = tuple(np.ascontiguousarray(f, dtype=float) if isinstance(f, np.ndarray) else f for f in form)
        object.__setattr__(self, "_form_cache", form)
        return form

    def _folded_values(self):
        """Values per table node, the last node of a periodic table carrying the first value."""
        if not self.periodic:
            return self.values
        v = self.values.copy()
        v[-1] = v[0]
        return v

    def _value_spline(self):
        sp = self.__dict__.get("_spline_cache")
        if sp is None:
            unit = _unit_spline(self.at.tobytes(), self.periodic)
            from scipy.interpolate import PPoly  # imported where used: scipy takes ~1 s to import, linear tables need none

            c = np.tensordot(unit.c, self._folded_values(), axes=([2], [0]))
            sp = PPoly(c, unit.x, extrapolate=True)
            object.__setattr__(self, "_spline_cache", sp)
        return sp

    def _wrap(self, q):
        if self.periodic:
            return self.at[0] + np.mod(q - self.at[0], TWO_PI)
        return q

    def basis(self, q: np.ndarray) -> np.ndarray:
        """(N, n) weights: value(q) = basis(q) @ values."""
        return self._basis(np.asarray(q, dtype=float), derivative=False)

    def basis_derivative(self, q: np.ndarray) -> np.ndarray:
        """(N, n): d basis / d q."""
        return self._basis(np.asarray(q, dtype=float), derivative=True)

    def _basis(self, q, derivative):
        B = self._basis_raw(q, derivative)
        if self.periodic and self.kind in ("linear", "cubic"):
            # The last node is the first one a turn later: its weight belongs to the first value.
            B[..., 0] += B[..., -1]
            B[..., -1] = 0.0
        return B

    def _basis_raw(self, q, derivative):
        n = self.values.size
        if self.kind == "linear":
            at = self.at
            x = self._wrap(q)
            inside = (x >= at[0]) & (x <= at[-1])
            xc = np.clip(x, at[0], at[-1])
            i = np.clip(np.searchsorted(at, xc, side="right") - 1, 0, n - 2)
            h = at[i + 1] - at[i]
            w = (xc - at[i]) / h
            B = np.zeros(q.shape + (n,))
            rows = np.arange(q.size).reshape(q.shape)
            if derivative:
                # Outside the table the value is held, so the slope is zero there.
                B[rows, i] = np.where(inside, -1.0 / h, 0.0)
                B[rows, i + 1] = np.where(inside, 1.0 / h, 0.0)
            else:
                B[rows, i] = 1.0 - w
                B[rows, i + 1] = w
            return B
        if self.kind == "cubic":
            x = self._wrap(q)
            spline = _unit_spline(self.at.tobytes(), self.periodic)
            inside = (x >= self.at[0]) & (x <= self.at[-1])
            xc = np.clip(x, self.at[0], self.at[-1])
            if derivative:
                return spline(xc, 1) * inside[..., None]
            return spline(xc)
        if self.kind == "legendre":
            lo, hi = self.domain
            x = np.clip((2.0 * q - (lo + hi)) / (hi - lo), -1.0, 1.0)
            if not derivative:
                return npleg.legvander(x, n - 1)
            inside = np.abs((2.0 * q - (lo + hi)) / (hi - lo)) <= 1.0
            cols = [npleg.legval(x, npleg.legder(np.eye(n)[k])) if k else np.zeros_like(x) for k in range(n)]
            return np.stack(cols, axis=-1) * (2.0 / (hi - lo)) * inside[..., None]
        if self.kind == "fourier":
            kq = q[..., None] * self.harmonics
            if derivative:
                cos_part, sin_part = -self.harmonics * np.sin(kq), self.harmonics * np.cos(kq)
            else:
                cos_part, sin_part = np.cos(kq), np.sin(kq)
            return np.stack([cos_part, sin_part], axis=-1).reshape(q.shape + (n,))
        raise ValueError(f"unknown error-function kind {self.kind!r}")


_SPLINES: dict = {}


def _unit_spline(at_bytes: bytes, periodic: bool):
    """A vector-valued cubic spline through the identity: its value at x is the cubic basis row at x (cached)."""
    key = (at_bytes, periodic)
    if key not in _SPLINES:
        from scipy.interpolate import CubicSpline


        at = np.frombuffer(at_bytes, dtype=float)
        unit = np.eye(at.size)
        if periodic:
            unit[-1] = unit[0]
        _SPLINES[key] = CubicSpline(at, unit, bc_type="periodic" if periodic else "not-a-knot")
    return _SPLINES[key]


_UNIT_COEFFICIENTS: dict = {}  # the disk cache's arrays, once read


def _unit_coefficients(at: np.ndarray, periodic: bool) -> np.ndarray:
    """(4, n - 1, n): the PPoly coefficients of ``_unit_spline`` (scipy's CubicSpline through the identity), read
    from a disk cache when there (the same numbers: scipy's, stored), else computed with scipy and stored. Importing
    scipy.interpolate costs the post about 0.25 s of CPU at start-up; the cache is filled by the first run (or
    ``python -m trueaxis.warm`` at install)."""
    key = (at.tobytes(), periodic)
    if key in _SPLINES:
        return _SPLINES[key].c
    if key in _UNIT_COEFFICIENTS:
        return _UNIT_COEFFICIENTS[key]
    import hashlib
    import os

    name = hashlib.sha256(key[0] + bytes([periodic])).hexdigest()[:32] + ".npy"
    path = _spline_cache_dir() / name
    n = at.size
    try:
        c = np.load(path, allow_pickle=False)
        if c.shape == (4, n - 1, n) and c.dtype == np.float64:
            _UNIT_COEFFICIENTS[key] = c
            return c
    except (OSError, ValueError):
        pass
    c = np.ascontiguousarray(_unit_spline(key[0], periodic).c, dtype=float)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.save(f, c, allow_pickle=False)
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only installation: computed each time
    return c


def _spline_cache_dir():
    """Where the unit splines' coefficients are kept: $TRUEAXIS_CACHE_DIR, else beside numba's kernel caches (this
    package's __pycache__)."""
    import os
    from pathlib import Path

    env = os.environ.get("TRUEAXIS_CACHE_DIR")
    return Path(env) / "splines" if env else Path(__file__).resolve().parent / "__pycache__" / "trueaxis_splines"


def table(at, values, interpolation: str = "linear", periodic: bool = False, label_unit: str = "mm") -> ErrorFunction:
    """A tabulated component error; ``at`` in internal units, ``values`` in um/urad."""
    at = np.asarray(at, dtype=float)
    values = np.asarray(values, dtype=float)
    scale = np.degrees(1.0) if label_unit == "deg" else 1.0
    labels = tuple(f"@{a * scale:g}" for a in at)
    if periodic:
        # The last node repeats the first one turn later: one free value less.
        return ErrorFunction(interpolation, values, at=at, periodic=True, labels=labels)
    return ErrorFunction(interpolation, values, at=at, labels=labels)


def legendre_series(coefficients, domain: tuple[float, float]) -> ErrorFunction:
    c = np.asarray(coefficients, dtype=float)
    return ErrorFunction("legendre", c, domain=domain, labels=tuple(f".P{k}" for k in range(c.size)))


def fourier_series(rows) -> ErrorFunction:
    """rows: [[k, a_k, b_k], ...] with k harmonics per revolution, amplitudes in um/urad."""
    rows = np.asarray(rows, dtype=float).reshape(-1, 3)
    k = rows[:, 0]
    values = rows[:, 1:].reshape(-1)
    labels = tuple(lab for kk in k for lab in (f".cos{kk:g}", f".sin{kk:g}"))
    return ErrorFunction("fourier", values, harmonics=k, labels=labels)
