"""Mechanistic milling forces of a flat, helical end mill, and their calibration against measured peak forces.

The model is the linear edge-force model of Altintas (Y. Altintas, *Manufacturing Automation*, 2nd ed., Cambridge
University Press 2012, ch. 2: "Mechanics of Metal Cutting", sections on the mechanics of milling and helical end
milling). On a cutting-edge element of axial height dz, engaged at immersion angle phi, with chip thickness
``h = fz * sin(phi)``:

    dF_t = (Ktc * h + Kte) dz        tangential, opposing the cutting speed
    dF_r = (Krc * h + Kre) dz        radial, pushing the edge towards the tool axis
    dF_a = (Kac * h + Kae) dz        axial

Ktc, Krc, Kac are cutting (shearing) coefficients in N/mm^2, Kte, Kre, Kae edge (ploughing) coefficients in N/mm. As in
Altintas, the chip width is the axial height dz (coefficients per mm of axial depth, not per mm of helical edge).

Frame and sign conventions (those of Altintas, stated exactly)
---------------------------------------------------------------
- x: the feed direction (the tool moves along +x relative to the workpiece).
- z: the tool axis, +z from the tool tip towards the spindle; the cut spans 0 <= z <= ap above the tip.
- y = z cross x (right-handed).
- The spindle turns clockwise seen from the spindle looking at the part (M3 with a right-hand cutter): the angular
  velocity is along -z.
- The immersion angle phi of an edge point is measured clockwise (seen from the spindle) from +y: the point sits at
  ``R * (sin(phi), cos(phi))`` in (x, y) and moves along ``(cos(phi), -sin(phi))``. Chip thickness is greatest at
  phi = pi/2, the front of the tool.
- Up milling: the material is on the +y side, ``R - ae <= y <= R``; an edge enters at phi_st = 0 with zero chip and
  leaves at phi_ex = arccos(1 - 2 ae / D).
- Down (climb) milling: the material is on the -y side, ``-R <= y <= -R + ae``; an edge enters at
  phi_st = arccos(2 ae / D - 1) with the thickest chip and leaves at phi_ex = pi.
- Slotting (ae = D): phi_st = 0, phi_ex = pi in both modes.
- Helix (right-hand, angle beta): a point at height z lags the tip of its flute by ``2 z tan(beta) / D``, so flute j at
  tool rotation angle ``phi`` sits at ``phi_j(z) = phi + j 2 pi / z_flutes - 2 z tan(beta) / D``.
- The force returned is the force exerted by the workpiece ON THE TOOL, in newtons, in the (x, y, z) feed frame:

      Fx = -dF_t cos(phi) - dF_r sin(phi)
      Fy = +dF_t sin(phi) - dF_r cos(phi)
      Fz = +dF_a

  summed over flutes and axial slices. The sign of the axial force is carried by the signs of Kac and Kae; the model
  imposes none. A dynamometer under the workpiece measures minus this force.
- ``phi`` in the outputs is the tool rotation angle: the immersion of flute 0 at the tool tip (z = 0).

Discretisation: ``n_angles`` rotation angles over one tooth period (the static force is periodic with it: no runout),
and ``n_slices`` axial slices at their mid-heights. Every engaged point is evaluated at once with numpy broadcasting
over (batch, angle, slice); only the few flutes are looped over. The engaged arc is the half-open interval
(phi_st, phi_ex], so ae = 0 or ap = 0 gives exactly zero force.

The geometry enters only through six sums over the engaged edge (``_edge_integrals``); the force is a fixed linear
map of those sums and the six coefficients. That makes the force exactly linear in the coefficients and makes the
calibration against measured peaks (``fit_coefficients``) cheap: the geometry is computed once, and the Jacobian of a
peak is the force basis at its maximising angle; cheap enough to run the solver from many starts, which the peaks'
local minima need.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Mapping, Sequence

import numpy as np

__all__ = [
    "CuttingCoefficients",
    "CuttingConditions",
    "engagement_angles",
    "force_history",
    "mean_force",
    "peak_force",
    "MeasuredPeakForces",
    "load_l16",
    "FitMinimum",
    "FitResult",
    "PLAUSIBLE_BOX",
    "TYPICAL_C45",
    "fit_coefficients",
]

COEFFICIENT_NAMES = ("Ktc", "Krc", "Kac", "Kte", "Kre", "Kae")


# --------------------------------------------------------------------------------------------------------------------
# Coefficients and cutting conditions
# --------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CuttingCoefficients:
    """The six coefficients of the linear edge-force model.

    Ktc, Krc, Kac : float, N/mm^2   cutting coefficients (tangential, radial, axial)
    Kte, Kre, Kae : float, N/mm     edge coefficients
    material : str                  free text, as in the machine file's ``[cutting]`` table
    """

    Ktc: float
    Krc: float
    Kac: float
    Kte: float
    Kre: float
    Kae: float
    material: str = ""

    NAMES: ClassVar[tuple[str, ...]] = COEFFICIENT_NAMES

    def __post_init__(self) -> None:
        for name in COEFFICIENT_NAMES:
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"cutting coefficient {name} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"cutting coefficient {name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, object]) -> "CuttingCoefficients":
        """From the machine file's ``[cutting]`` table: keys Ktc Krc Kac Kte Kre Kae (all required), material."""
        unknown = set(mapping) - set(COEFFICIENT_NAMES) - {"material"}
        if unknown:
            raise ValueError(
                f"[cutting]: unknown keys {sorted(unknown)}; expected {list(COEFFICIENT_NAMES)} and material"
            )
        missing = [name for name in COEFFICIENT_NAMES if name not in mapping]
        if missing:
            raise ValueError(f"[cutting]: missing keys {missing}")
        return cls(*(mapping[name] for name in COEFFICIENT_NAMES), material=str(mapping.get("material", "")))

    @classmethod
    def from_array(cls, values: Sequence[float], material: str = "") -> "CuttingCoefficients":
        """From (6,) values in the order Ktc, Krc, Kac (N/mm^2), Kte, Kre, Kae (N/mm)."""
        values = np.asarray(values, dtype=float).ravel()
        if values.shape != (6,):
            raise ValueError(f"expected 6 coefficients (Ktc, Krc, Kac, Kte, Kre, Kae), got {values.size}")
        return cls(*values.tolist(), material=material)

    def as_array(self) -> np.ndarray:
        """(6,) float: Ktc, Krc, Kac (N/mm^2), Kte, Kre, Kae (N/mm)."""
        return np.array([getattr(self, name) for name in COEFFICIENT_NAMES])

    def as_mapping(self) -> dict[str, object]:
        """The machine file's ``[cutting]`` table."""
        out: dict[str, object] = {"material": self.material} if self.material else {}
        out.update({name: getattr(self, name) for name in COEFFICIENT_NAMES})
        return out


@dataclass(frozen=True, eq=False)
class CuttingConditions:
    """Cutting conditions of a flat end mill; ap, ae, fz may be arrays that broadcast to one batch shape.

    ap_mm : float or (...) array, mm      axial depth of cut, >= 0
    ae_mm : float or (...) array, mm      radial engagement, 0 <= ae <= D
    fz_mm : float or (...) array, mm      feed per tooth, >= 0
    tool_diameter_mm : float, mm          D > 0
    flutes : int                          z >= 1, evenly spaced
    helix_deg : float, deg                0 <= helix < 90 (right-hand helix)
    mode : "down" | "up"                  see the module docstring for which side the material is on
    spindle_rpm : float or None           does not enter the static force; gives the feed rate fz * z * n

    Arrays are stored as float ndarrays (so instances compare by identity, not value).
    """

    ap_mm: float | np.ndarray
    ae_mm: float | np.ndarray
    fz_mm: float | np.ndarray
    tool_diameter_mm: float
    flutes: int
    helix_deg: float = 30.0
    mode: str = "down"
    spindle_rpm: float | None = None
    batch_shape: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        D = float(self.tool_diameter_mm)
        if not (math.isfinite(D) and D > 0.0):
            raise ValueError(f"tool diameter must be positive, got {self.tool_diameter_mm!r} mm")
        if isinstance(self.flutes, bool) or int(self.flutes) != self.flutes or int(self.flutes) < 1:
            raise ValueError(f"flutes must be a positive integer, got {self.flutes!r}")
        helix = float(self.helix_deg)
        if not (0.0 <= helix < 90.0):
            raise ValueError(f"helix angle must be in [0, 90) deg, got {self.helix_deg!r}")
        if self.mode not in ("down", "up"):
            raise ValueError(f"mode must be 'down' or 'up', got {self.mode!r}")
        if self.spindle_rpm is not None and not (float(self.spindle_rpm) > 0.0):
            raise ValueError(f"spindle speed must be positive, got {self.spindle_rpm!r} rpm")
        arrays = {}
        for name in ("ap_mm", "ae_mm", "fz_mm"):
            value = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be finite")
            if np.any(value < 0.0):
                raise ValueError(f"{name} must not be negative, got {value.min():g} mm")
            arrays[name] = value
        if np.any(arrays["ae_mm"] > D * (1.0 + 1e-12)):
            raise ValueError(
                f"radial engagement ae = {arrays['ae_mm'].max():g} mm exceeds the tool diameter D = {D:g} mm"
            )
        try:
            shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
        except ValueError:
            raise ValueError("ap_mm, ae_mm and fz_mm do not broadcast to one batch shape") from None
        for name, value in arrays.items():
            object.__setattr__(self, name, float(value) if value.ndim == 0 else value)
        object.__setattr__(self, "ae_mm", np.minimum(self.ae_mm, D) if np.ndim(self.ae_mm) else min(self.ae_mm, D))
        object.__setattr__(self, "tool_diameter_mm", D)
        object.__setattr__(self, "flutes", int(self.flutes))
        object.__setattr__(self, "helix_deg", helix)
        object.__setattr__(self, "batch_shape", tuple(shape))

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, object]) -> "CuttingConditions":
        """From the program comment's fields ``ap ae fz n d z mode`` (DESIGN §5), plus optional ``helix``."""
        unknown = set(mapping) - {"ap", "ae", "fz", "n", "d", "z", "mode", "helix"}
        if unknown:
            raise ValueError(f"unknown cutting-condition fields {sorted(unknown)}")
        missing = [key for key in ("ap", "ae", "fz", "d", "z") if key not in mapping]
        if missing:
            raise ValueError(f"missing cutting-condition fields {missing}")
        return cls(
            ap_mm=float(mapping["ap"]),
            ae_mm=float(mapping["ae"]),
            fz_mm=float(mapping["fz"]),
            tool_diameter_mm=float(mapping["d"]),
            flutes=int(mapping["z"]),
            helix_deg=float(mapping.get("helix", 30.0)),
            mode=str(mapping.get("mode", "down")),
            spindle_rpm=None if mapping.get("n") is None else float(mapping["n"]),
        )

    @property
    def feed_rate_mm_min(self) -> float | np.ndarray | None:
        """Feed rate fz * z * n, mm/min (None without a spindle speed)."""
        if self.spindle_rpm is None:
            return None
        return self.fz_mm * self.flutes * float(self.spindle_rpm)


def engagement_angles(conditions: CuttingConditions) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit immersion angles (phi_st, phi_ex), each of the batch shape, rad (Altintas ch. 2)."""
    ratio = np.clip(2.0 * np.asarray(conditions.ae_mm, dtype=float) / conditions.tool_diameter_mm, 0.0, 2.0)
    ratio = np.broadcast_to(ratio, conditions.batch_shape)
    if conditions.mode == "up":
        return np.zeros(ratio.shape), np.arccos(1.0 - ratio)
    return np.arccos(ratio - 1.0), np.full(ratio.shape, np.pi)


# --------------------------------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------------------------------


def _default_slices(conditions: CuttingConditions, n_angles: int) -> int:
    """Enough axial slices that the helix lag across one slice is no larger than the angle step (at least 1)."""
    lag_total = 2.0 * np.max(conditions.ap_mm, initial=0.0) * math.tan(math.radians(conditions.helix_deg))
    lag_total /= conditions.tool_diameter_mm
    step = 2.0 * math.pi / conditions.flutes / n_angles
    return int(min(max(1, math.ceil(lag_total / step)), 4096))


def _edge_integrals(
    conditions: CuttingConditions, n_angles: int, n_slices: int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Sums over the engaged edge that the force is linear in.

    Returns phi : (M,) float, rad, tool rotation angles over one tooth period, and S : (*batch, M, 6) float with
    S = [sum h cos(phi) dz, sum h sin(phi) dz, sum h dz  (mm^2),  sum cos(phi) dz, sum sin(phi) dz, sum dz  (mm)],
    each sum over flutes and axial slices of the engaged points (h = fz sin(phi), phi the immersion of the point).
    """
    if int(n_angles) != n_angles or n_angles < 1:
        raise ValueError(f"n_angles must be a positive integer, got {n_angles!r}")
    if n_slices is None:
        n_slices = _default_slices(conditions, int(n_angles))
    if int(n_slices) != n_slices or n_slices < 1:
        raise ValueError(f"n_slices must be a positive integer, got {n_slices!r}")
    M, K, N = int(n_angles), int(n_slices), conditions.flutes
    pitch = 2.0 * np.pi / N
    phi = np.arange(M) * (pitch / M)  # (M,) one tooth period, starting at flute 0's tip at +y

    shape = conditions.batch_shape
    ap = np.broadcast_to(conditions.ap_mm, shape).reshape(-1, 1, 1)  # (B,1,1)
    fz = np.broadcast_to(conditions.fz_mm, shape).reshape(-1, 1, 1)
    phi_st, phi_ex = (a.reshape(-1, 1, 1) for a in engagement_angles(conditions))
    dz = ap / K  # (B,1,1) axial height of a slice, mm
    z = (np.arange(K) + 0.5).reshape(1, 1, K) * dz  # (B,1,K) slice mid-heights above the tip
    lag = z * (2.0 * math.tan(math.radians(conditions.helix_deg)) / conditions.tool_diameter_mm)  # (B,1,K) rad

    S = np.zeros((ap.shape[0], M, 6))
    for j in range(N):  # a handful of flutes; everything inside is broadcast over (batch, angle, slice)
        immersion = np.mod(phi.reshape(1, M, 1) + j * pitch - lag, 2.0 * np.pi)  # (B,M,K)
        # Half-open engaged arc (phi_st, phi_ex]: ae = 0 gives an empty arc, hence exactly zero force.
        engaged = (immersion > phi_st) & (immersion <= phi_ex)
        w = engaged * dz  # (B,M,K) chip width of engaged points, mm
        s, c = np.sin(immersion), np.cos(immersion)
        h = fz * s  # chip thickness, mm (>= 0 on the engaged arc, which lies in [0, pi])
        S[..., 0] += np.sum(w * h * c, axis=-1)
        S[..., 1] += np.sum(w * h * s, axis=-1)
        S[..., 2] += np.sum(w * h, axis=-1)
        S[..., 3] += np.sum(w * c, axis=-1)
        S[..., 4] += np.sum(w * s, axis=-1)
        S[..., 5] += np.sum(w, axis=-1)
    return phi, S.reshape(shape + (M, 6))


# Force = S @ _BASIS @ K, with S the edge integrals (.., 6) and K the coefficients (Ktc, Krc, Kac, Kte, Kre, Kae):
#   Fx = -(Ktc Shc + Kte Sc) - (Krc Shs + Kre Ss)
#   Fy = +(Ktc Shs + Kte Ss) - (Krc Shc + Kre Sc)
#   Fz = +(Kac Sh + Kae S1)
# (Altintas' projection Fx = -Ft cos(phi) - Fr sin(phi), Fy = Ft sin(phi) - Fr cos(phi), Fz = Fa, summed.)
_SHC, _SHS, _SH, _SC, _SS, _S1 = range(6)  # integral index
_KTC, _KRC, _KAC, _KTE, _KRE, _KAE = range(6)  # coefficient index
_BASIS = np.zeros((6, 3, 6))  # [integral, force component, coefficient]
for _integral, _component, _coefficient, _sign in [
    (_SHC, 0, _KTC, -1.0), (_SC, 0, _KTE, -1.0), (_SHS, 0, _KRC, -1.0), (_SS, 0, _KRE, -1.0),
    (_SHS, 1, _KTC, +1.0), (_SS, 1, _KTE, +1.0), (_SHC, 1, _KRC, -1.0), (_SC, 1, _KRE, -1.0),
    (_SH, 2, _KAC, +1.0), (_S1, 2, _KAE, +1.0),
]:
    _BASIS[_integral, _component, _coefficient] = _sign


def _unit_forces(S: np.ndarray) -> np.ndarray:
    """(..., 6) edge integrals -> (..., 3, 6): the force (N) per unit of each coefficient."""
    return np.einsum("...i,ick->...ck", S, _BASIS)


def force_history(
    coeffs: CuttingCoefficients,
    conditions: CuttingConditions,
    n_angles: int = 360,
    n_slices: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Cutting force on the tool over one tooth period.

    coeffs : CuttingCoefficients
    conditions : CuttingConditions with batch shape (...)
    n_angles : int, M, rotation angles per tooth period (step 2 pi / (z M))
    n_slices : int or None, axial slices; None: enough that the helix lag across a slice is at most one angle step

    Returns phi : (M,) float, rad, tool rotation angle (flute 0 at the tip, clockwise from +y), and
    force : (..., M, 3) float, N, (Fx, Fy, Fz) exerted by the workpiece on the tool, feed frame.
    """
    phi, S = _edge_integrals(conditions, n_angles, n_slices)
    return phi, _unit_forces(S) @ coeffs.as_array()


def mean_force(
    coeffs: CuttingCoefficients, conditions: CuttingConditions, n_angles: int = 360, n_slices: int | None = None
) -> np.ndarray:
    """Average force on the tool over a tooth period: (..., 3) float, N, feed frame (rectangle rule over n_angles)."""
    return force_history(coeffs, conditions, n_angles, n_slices)[1].mean(axis=-2)


def peak_force(
    coeffs: CuttingCoefficients, conditions: CuttingConditions, n_angles: int = 360, n_slices: int | None = None
) -> np.ndarray:
    """Largest magnitude of each component over a tooth period, max |F_i|: (..., 3) float, N, feed frame.

    Sign-free, so it compares with a dynamometer's peaks whichever body it measures. Note that as ae -> 0 the mean
    force tends to zero but the peak tends to the edge force ap * (Kte, Kre, Kae) of one tooth (while an angle sample
    still falls inside the shrinking arc): the edge force does not scale with the chip.
    """
    return np.abs(force_history(coeffs, conditions, n_angles, n_slices)[1]).max(axis=-2)


# --------------------------------------------------------------------------------------------------------------------
# Measured peak forces (the L16 test) and the calibration
# --------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MeasuredPeakForces:
    """Peak forces of a milling test, one row per test group; every array is (G,).

    group : int;  ap_mm, fz_mm, ae_mm : float, mm;  ae_inferred : bool;  feed_mm_min : float, mm/min;
    fs_hz : float, Hz;  fx_max_n, fy_max_n : float, N;  comments : the file's ``#`` header lines (source, notes).
    """

    group: np.ndarray
    ap_mm: np.ndarray
    fz_mm: np.ndarray
    ae_mm: np.ndarray
    ae_inferred: np.ndarray
    feed_mm_min: np.ndarray
    fs_hz: np.ndarray
    fx_max_n: np.ndarray
    fy_max_n: np.ndarray
    comments: tuple[str, ...] = ()

    @property
    def peaks_n(self) -> np.ndarray:
        """(G, 2) float, N: measured (Fx_max, Fy_max)."""
        return np.stack([self.fx_max_n, self.fy_max_n], axis=-1)


def load_l16(path: str | Path) -> MeasuredPeakForces:
    """Read ``milling_forces_l16.csv`` (``#`` comment header, then a CSV table with a header row)."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    comments = tuple(line[1:].strip() for line in lines if line.startswith("#"))
    rows = list(csv.DictReader(line for line in lines if line.strip() and not line.startswith("#")))
    if not rows:
        raise ValueError(f"{path}: no data rows")
    needed = ["group", "ap_mm", "fz_mm", "ae_mm", "ae_inferred", "feed_mm_min", "fs_hz", "fx_max_n", "fy_max_n"]
    missing = [name for name in needed if name not in rows[0]]
    if missing:
        raise ValueError(f"{path}: missing columns {missing}")

    def column(name: str, kind=float) -> np.ndarray:
        try:
            return np.array([kind(row[name]) for row in rows])
        except (TypeError, ValueError) as error:
            raise ValueError(f"{path}: column {name}: {error}") from None

    return MeasuredPeakForces(
        group=column("group", int),
        ap_mm=column("ap_mm"),
        fz_mm=column("fz_mm"),
        ae_mm=column("ae_mm"),
        ae_inferred=np.array([row["ae_inferred"].strip().lower() == "yes" for row in rows]),
        feed_mm_min=column("feed_mm_min"),
        fs_hz=column("fs_hz"),
        fx_max_n=column("fx_max_n"),
        fy_max_n=column("fy_max_n"),
        comments=comments,
    )


# Kac and Kae cannot be seen in peak Fx, Fy: they stay at these values (typical C45 figures, see
# ../shared/data/typical_error_magnitudes.md), and so do the starting values of the fitted ones.
TYPICAL_C45 = CuttingCoefficients(2000.0, 750.0, 400.0, 30.0, 45.0, 5.0, material="C45")

# The box of plausible coefficients the multi-start fit draws its starting points from (lower, upper), N/mm^2 for the
# cutting and N/mm for the edge coefficients: twice the typical steel figures for the cutting coefficients (Ktc of
# steels 1500-2500 N/mm^2), and edge coefficients up to 500 N/mm, beyond any published figure (tens of N/mm) since
# peak-force data can push the force into them (the L16 fit does: Kte ~ 250 N/mm).
PLAUSIBLE_BOX: dict[str, tuple[float, float]] = {
    "Ktc": (0.0, 4000.0), "Krc": (0.0, 2000.0), "Kac": (0.0, 2000.0),
    "Kte": (0.0, 500.0), "Kre": (0.0, 500.0), "Kae": (0.0, 500.0),
}


@dataclass(frozen=True)
class FitMinimum:
    """One local minimum of the least-squares fit: the coefficients (the unfitted ones at their fixed values), the RMS
    residual (N) there, and how many of the starting points ended in it."""

    coefficients: CuttingCoefficients
    rms_n: float
    starts: int


@dataclass(frozen=True, eq=False)
class FitResult:
    """Coefficients fitted to measured peak forces, and how well they fit.

    coefficients : CuttingCoefficients at the best minimum found (the unfitted ones at their fixed values)
    fitted : tuple of the fitted coefficient names;  std_errors : {name: standard error} in the coefficient's unit,
        linearised at the best minimum
    groups : (G,) int;  measured_n, predicted_n, residuals_n : (G, 2) float, N, columns (Fx_max, Fy_max),
        residual = predicted - measured
    r2_fx, r2_fy, r2 : coefficient of determination 1 - SSR/SST (each component about its own mean; r2 over all
        2G values about their common mean)
    rms_n, rms_fx_n, rms_fy_n : RMS residual, N
    worst_group : int, worst_component : "Fx" | "Fy", worst_residual_n : float, N (signed, predicted - measured)
    assumptions : dict of what the data do not give (tool, mode, how the paper's forces are read, discretisation)
    r2_proportional_to_ap : (2,) float, R^2 of Fx, Fy for the baseline "peak = constant * ap" (one constant per
        component), to show what the mechanistic model adds
    data : MeasuredPeakForces, the groups fitted
    minima : the distinct local minima the starts ended in, best first (the first is the fit above)
    near_equal_rms_n : float, N: minima with an RMS up to this are near-equal to the best: inside the data's 95 %
        joint confidence region of the coefficients (SSR <= SSR_best (1 + p / (n - p) F(0.95; p, n - p)), Beale's
        likelihood region, n residuals, p fitted coefficients), so the data cannot tell them from the best
    spread : {name: (lowest, highest)} of each fitted coefficient over the near-equal minima
    poorly_identified : names of the fitted coefficients whose spread over the near-equal minima exceeds their
        standard error: the linearised error bar understates their uncertainty, and the data do not pin them down
    """

    coefficients: CuttingCoefficients
    fitted: tuple[str, ...]
    std_errors: dict[str, float]
    groups: np.ndarray
    measured_n: np.ndarray
    predicted_n: np.ndarray
    residuals_n: np.ndarray
    r2_fx: float
    r2_fy: float
    r2: float
    rms_n: float
    rms_fx_n: float
    rms_fy_n: float
    worst_group: int
    worst_component: str
    worst_residual_n: float
    assumptions: dict[str, object]
    r2_proportional_to_ap: np.ndarray
    data: MeasuredPeakForces
    minima: tuple[FitMinimum, ...] = ()
    near_equal_rms_n: float = float("nan")
    spread: dict[str, tuple[float, float]] = field(default_factory=dict)
    poorly_identified: tuple[str, ...] = ()


def _r2(measured: np.ndarray, residual: np.ndarray) -> float:
    return float(1.0 - np.sum(residual**2) / np.sum((measured - measured.mean()) ** 2))


def _distinct_minima(x: np.ndarray, rms: np.ndarray, scale: np.ndarray, tol: float, rms_tol_n: float):
    """Group the (S, p) end points ``x`` with RMS ``rms`` (S,) into distinct minima, best first.

    Greedy and deterministic: the ends are taken in order of RMS; an end joins the first representative within ``tol``
    of the box width ``scale`` (p,) in every coefficient and ``rms_tol_n`` in RMS, else it starts a new minimum (flat
    valleys, whose ends lie a little apart at one RMS, so stay one minimum). Returns (representative indices, counts).
    """
    order = np.lexsort((np.arange(rms.size), rms))
    reps: list[int] = []
    counts: list[int] = []
    for i in order:
        for r, rep in enumerate(reps):
            if abs(rms[i] - rms[rep]) <= rms_tol_n and np.all(np.abs(x[i] - x[rep]) <= tol * scale):
                counts[r] += 1
                break
        else:
            reps.append(int(i))
            counts.append(1)
    return reps, counts


def fit_coefficients(
    groups: MeasuredPeakForces,
    *,
    tool_diameter_mm: float = 10.0,
    flutes: int = 4,
    helix_deg: float = 30.0,
    mode: str = "down",
    fit: Sequence[str] = ("Ktc", "Krc", "Kte", "Kre"),
    fixed: CuttingCoefficients = TYPICAL_C45,
    n_angles: int = 360,
    n_slices: int | None = None,
    starts: int = 64,
    seed: int = 0,
) -> FitResult:
    """Fit the coefficients named in ``fit`` to the measured peak |Fx|, |Fy| by bounded least squares, from many starts.

    The paper's Fx, Fy are read as components in the feed frame (x along the feed, y across it); the model's peak is
    max over a tooth period of |F_x| and |F_y| (``peak_force``). Residuals are in newtons, unweighted. The fitted
    coefficients are bounded to be non-negative (scipy.optimize.least_squares, trust-region reflective); the others
    keep their values in ``fixed``.

    The peak is the force at its maximising angle, which jumps as the coefficients change: the sum of squares is
    piecewise quadratic with several local minima (three on the L16 data with the default assumptions). So the solver
    runs from the values in ``fixed`` and from ``starts`` more points, a Latin hypercube (scipy.stats.qmc, seeded with
    ``seed``) over ``PLAUSIBLE_BOX``; the ends are grouped into distinct minima (``FitResult.minima``), and the best is
    returned.
    With 64 starts each L16 fit of docs/force_fit.md reaches its best minimum from 12 or more of them.
    Standard errors: sqrt(diag(s^2 (J^T J)^-1)), s^2 = SSR / (2G - p), with J the exact Jacobian (the force basis at
    each peak's maximising angle) at the best minimum. The spread of each coefficient over the minima that the data
    cannot tell from the best is in ``FitResult.spread`` and ``poorly_identified``. Deterministic: the same input
    gives the same result.
    """
    # scipy imported here, not at the top: the post imports this module and must not wait ~1 s for scipy.optimize
    from scipy.optimize import least_squares
    from scipy.stats import f as f_distribution
    from scipy.stats import qmc

    unknown = [name for name in fit if name not in COEFFICIENT_NAMES]
    if unknown or not fit:
        raise ValueError(f"fit must name some of {list(COEFFICIENT_NAMES)}, got {list(fit)}")
    if int(starts) != starts or starts < 0:
        raise ValueError(f"starts must be a non-negative integer, got {starts!r}")
    conditions = CuttingConditions(
        ap_mm=groups.ap_mm, ae_mm=groups.ae_mm, fz_mm=groups.fz_mm, tool_diameter_mm=tool_diameter_mm,
        flutes=flutes, helix_deg=helix_deg, mode=mode,
    )
    _, S = _edge_integrals(conditions, n_angles, n_slices)
    unit = _unit_forces(S)[..., :2, :]  # (G, M, 2, 6): Fx, Fy per unit coefficient
    fit = tuple(fit)
    index = [COEFFICIENT_NAMES.index(name) for name in fit]
    base = fixed.as_array()
    measured = groups.peaks_n  # (G, 2)
    G = measured.shape[0]
    p_count = len(index)

    def coefficients_of(p: np.ndarray) -> np.ndarray:
        k = base.copy()
        k[index] = p
        return k

    def peaks_and_argmax(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        force = unit @ coefficients_of(p)  # (G, M, 2)
        at = np.abs(force).argmax(axis=1)  # (G, 2) maximising angle of each peak
        f_at = np.take_along_axis(force, at[:, None, :], axis=1)[:, 0, :]  # (G, 2) signed force there
        return f_at, at

    def residuals(p: np.ndarray) -> np.ndarray:
        f_at, _ = peaks_and_argmax(p)
        return (np.abs(f_at) - measured).ravel()

    def jacobian(p: np.ndarray) -> np.ndarray:
        # |F| at its maximising angle is linear in the coefficients there: d|F|/dK = sign(F) * unit force.
        f_at, at = peaks_and_argmax(p)
        unit_at = np.take_along_axis(unit, at[:, None, :, None], axis=1)[:, 0]  # (G, 2, 6)
        return (np.sign(f_at)[..., None] * unit_at[..., index]).reshape(2 * G, p_count)

    # Starting points: the given values first, then a Latin hypercube over the plausible box.
    lower = np.array([PLAUSIBLE_BOX[name][0] for name in fit])
    upper = np.array([PLAUSIBLE_BOX[name][1] for name in fit])
    p_starts = [np.maximum(base[index], 1e-3)]
    if starts:
        unit_cube = qmc.LatinHypercube(d=p_count, seed=seed).random(int(starts))
        p_starts += list(np.maximum(lower + unit_cube * (upper - lower), 1e-3))
    ends, costs, statuses = [], [], []
    for p0 in p_starts:
        sol = least_squares(residuals, p0, jac=jacobian, bounds=(0.0, np.inf), method="trf", x_scale="jac")
        ends.append(sol.x)
        costs.append(float(np.sqrt(np.mean(residuals(sol.x) ** 2))))
        statuses.append(int(sol.status))
    ends_arr, rms_arr = np.array(ends), np.array(costs)
    reps, counts = _distinct_minima(ends_arr, rms_arr, upper - lower, tol=0.01,
                                    rms_tol_n=1e-3 * max(rms_arr.min(), 1.0))
    best = reps[0]
    p = ends_arr[best]
    minima = tuple(
        FitMinimum(CuttingCoefficients.from_array(coefficients_of(ends_arr[r]), material=fixed.material),
                   float(rms_arr[r]), int(c))
        for r, c in zip(reps, counts)
    )

    residual = residuals(p).reshape(G, 2)
    J = jacobian(p)
    n_res = 2 * G
    dof = max(n_res - p_count, 1)
    ssr = float(np.sum(residual**2))
    s2 = ssr / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    std = dict(zip(fit, np.sqrt(np.clip(np.diag(cov), 0.0, None)).tolist()))

    # Near-equal minima: inside Beale's 95 % joint confidence region of the best one.
    ssr_bound = ssr * (1.0 + p_count / dof * float(f_distribution.ppf(0.95, p_count, dof)))
    near_equal_rms = float(np.sqrt(ssr_bound / n_res))
    near = [mn for mn in minima if mn.rms_n <= near_equal_rms]
    spread = {
        name: (min(getattr(mn.coefficients, name) for mn in near), max(getattr(mn.coefficients, name) for mn in near))
        for name in fit
    }
    poorly = tuple(name for name in fit if spread[name][1] - spread[name][0] > std[name])

    # Baseline: each peak proportional to ap alone (least squares through the origin).
    ap = groups.ap_mm[:, None]
    baseline = ap * (np.sum(ap * measured, axis=0) / np.sum(ap * ap)) - measured
    r2_ap = np.array([_r2(measured[:, c], baseline[:, c]) for c in range(2)])

    flat = np.abs(residual).ravel().argmax()
    worst_g, worst_c = divmod(int(flat), 2)
    return FitResult(
        coefficients=minima[0].coefficients,
        fitted=fit,
        std_errors=std,
        groups=groups.group.copy(),
        measured_n=measured,
        predicted_n=measured + residual,
        residuals_n=residual,
        r2_fx=_r2(measured[:, 0], residual[:, 0]),
        r2_fy=_r2(measured[:, 1], residual[:, 1]),
        r2=_r2(measured.ravel(), residual.ravel()),
        rms_n=float(np.sqrt(np.mean(residual**2))),
        rms_fx_n=float(np.sqrt(np.mean(residual[:, 0] ** 2))),
        rms_fy_n=float(np.sqrt(np.mean(residual[:, 1] ** 2))),
        worst_group=int(groups.group[worst_g]),
        worst_component=("Fx", "Fy")[worst_c],
        worst_residual_n=float(residual[worst_g, worst_c]),
        assumptions={
            "tool_diameter_mm": float(tool_diameter_mm),
            "flutes": int(flutes),
            "helix_deg": float(helix_deg),
            "mode": mode,
            "force_reading": "Fx_max, Fy_max = max over a tooth period of |Fx|, |Fy|, x along the feed, y across it",
            "fixed": {name: float(base[i]) for i, name in enumerate(COEFFICIENT_NAMES) if name not in fit},
            "n_angles": int(n_angles),
            "n_slices": None if n_slices is None else int(n_slices),
            "starts": len(p_starts),
            "seed": int(seed),
            "start_box": {name: PLAUSIBLE_BOX[name] for name in fit},
            "solver_status": statuses[best],
        },
        r2_proportional_to_ap=r2_ap,
        data=groups,
        minima=minima,
        near_equal_rms_n=near_equal_rms,
        spread=spread,
        poorly_identified=poorly,
    )
