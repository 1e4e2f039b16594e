"""Turning forces from the specific cutting force (Kienzle), and their direction on a two-axis lathe.

The main (cutting) force of a single-point turning tool follows Kienzle's law (O. Kienzle, "Die Bestimmung von Kräften
und Leistungen an spanenden Werkzeugen und Werkzeugmaschinen", VDI-Z 94 (1952) 299-305; F. Klocke, *Manufacturing
Processes 1: Cutting*, Springer 2011, ch. 5):

    h = f sin(kappa_r)          undeformed chip thickness, mm (f: feed per revolution, mm/rev)
    b = ap / sin(kappa_r)       chip width, mm (ap: depth of cut, mm)
    Fc = kc1.1 * b * h^(1 - mc) main cutting force, N (kc1.1: specific cutting force at h = b = 1 mm, N/mm^2)

kappa_r is the tool cutting-edge angle (90 deg unless the machine file says otherwise). The feed force Ff and the
passive force Fp are taken as fixed fractions of Fc (``feed_ratio``, ``passive_ratio``; Klocke gives Ff/Fc and
Fp/Fc of about 0.2-0.5 for steels), the cutting speed optionally through Kienzle's speed correction
Fc *= (vc_ref / vc)^vc_exponent (off unless the machine file gives ``vc_exponent``: kc1.1 is then taken as valid at
the program's speed).

Directions, machine frame of a two-axis lathe (ISO 841: Z along the spindle axis, X radial, the tool moving relative to
the workpiece; Y = Z x X): for a cut moving the tool along the unit direction d in the XZ plane,

- the feed force opposes the feed:                         -Ff d
- the passive force pushes the tool away from the material: +Fp n, n the normal to d in the XZ plane on the side of
  +X +Z (n_x + n_z > 0): external turning of a part towards the chuck, the material lying towards the spindle axis
  (-X) and the chuck (-Z), so longitudinal cuts get n = +X and facing cuts n = +Z. On the diagonal d = +-(1, 1)
  (n_x + n_z = 0) n_x > 0 is taken;
- the main force acts along the workpiece's surface speed at the tool: +Fc Y.

So longitudinal turning towards the chuck (d = -Z) loads the tool with +Ff along Z and +Fp along X, turning towards the
tailstock with -Ff along Z, facing with +Fp along Z and -+Ff along X. Internal turning (boring) and tools behind the
spindle line are not modelled: their passive force has the other sign.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

__all__ = ["TURNING_KEYS", "TurningCoefficients", "TurningConditions", "turning_force_components", "force_on_tool"]

# Keys of a lathe's [cutting] table (DESIGN §4 extended for turning); kc11 and mc are required.
TURNING_KEYS = ("kc11", "mc", "feed_ratio", "passive_ratio", "kappa_deg", "vc_ref", "vc_exponent")


@dataclass(frozen=True)
class TurningCoefficients:
    """A work material's turning coefficients (the lathe machine file's ``[cutting]`` table).

    kc11 : float, N/mm^2   specific cutting force at h = b = 1 mm
    mc : float             Kienzle's exponent, 0 <= mc < 1
    feed_ratio, passive_ratio : float   Ff / Fc and Fp / Fc, >= 0
    kappa_deg : float, deg  tool cutting-edge angle, 0 < kappa_r <= 180
    vc_ref : float, m/min;  vc_exponent : float   Kienzle's speed correction (vc_exponent 0: none)
    material : str
    """

    kc11: float
    mc: float
    feed_ratio: float = 0.0
    passive_ratio: float = 0.0
    kappa_deg: float = 90.0
    vc_ref: float = 100.0
    vc_exponent: float = 0.0
    material: str = ""

    def __post_init__(self) -> None:
        for name in ("kc11", "mc", "feed_ratio", "passive_ratio", "kappa_deg", "vc_ref", "vc_exponent"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"[cutting] {name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.kc11 <= 0.0:
            raise ValueError(f"[cutting] kc11 must be positive, got {self.kc11!r} N/mm^2")
        if not 0.0 <= self.mc < 1.0:
            raise ValueError(f"[cutting] mc must lie in [0, 1), got {self.mc!r}")
        if self.feed_ratio < 0.0 or self.passive_ratio < 0.0:
            raise ValueError("[cutting] feed_ratio and passive_ratio must not be negative")
        if not 0.0 < self.kappa_deg <= 180.0:
            raise ValueError(f"[cutting] kappa_deg must lie in (0, 180], got {self.kappa_deg!r}")
        if self.vc_ref <= 0.0:
            raise ValueError(f"[cutting] vc_ref must be positive, got {self.vc_ref!r} m/min")

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, object]) -> "TurningCoefficients":
        """From the lathe machine file's ``[cutting]`` table: kc11 and mc required, the rest optional."""
        unknown = set(mapping) - set(TURNING_KEYS) - {"material"}
        if unknown:
            raise ValueError(f"[cutting]: unknown keys {sorted(unknown)} for turning; expected {list(TURNING_KEYS)}")
        missing = [key for key in ("kc11", "mc") if key not in mapping]
        if missing:
            raise ValueError(f"[cutting]: turning needs {missing} (Kienzle's kc1.1 in N/mm^2 and mc)")
        values = {key: mapping[key] for key in TURNING_KEYS if key in mapping}
        return cls(**values, material=str(mapping.get("material", "")))


@dataclass(frozen=True)
class TurningConditions:
    """Cutting conditions of a turning pass (the program comment ``(trueaxis: ap=2 f=0.2 vc=180)``).

    ap_mm : float, mm         depth of cut, > 0
    f_mm : float, mm/rev      feed per revolution, > 0
    vc_m_min : float or None  cutting speed, m/min, > 0 (needed only with a speed correction)
    """

    ap_mm: float
    f_mm: float
    vc_m_min: float | None = None

    def __post_init__(self) -> None:
        for name in ("ap_mm", "f_mm", "vc_m_min"):
            value = getattr(self, name)
            if value is None and name == "vc_m_min":
                continue
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {value!r}") from None
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive, got {value!r}")
            object.__setattr__(self, name, value)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, object]) -> "TurningConditions":
        """From the program comment's fields ``ap f vc`` (DESIGN §5)."""
        unknown = set(mapping) - {"ap", "f", "vc"}
        if unknown:
            raise ValueError(f"unknown turning-condition fields {sorted(unknown)} (turning: ap f vc)")
        missing = [key for key in ("ap", "f") if key not in mapping]
        if missing:
            raise ValueError(f"missing turning-condition fields {missing}")
        vc = mapping.get("vc")
        return cls(ap_mm=mapping["ap"], f_mm=mapping["f"], vc_m_min=None if vc is None else vc)


def turning_force_components(coeffs: TurningCoefficients, conditions: TurningConditions) -> tuple[float, float, float]:
    """(Fc, Ff, Fp) in N: Kienzle's main cutting force, and the feed and passive forces as its fractions."""
    kappa = math.radians(coeffs.kappa_deg)
    h = conditions.f_mm * math.sin(kappa)
    b = conditions.ap_mm / math.sin(kappa)
    fc = coeffs.kc11 * b * h ** (1.0 - coeffs.mc)
    if coeffs.vc_exponent != 0.0:
        if conditions.vc_m_min is None:
            raise ValueError("the speed correction (vc_exponent) needs the cutting speed vc")
        fc *= (coeffs.vc_ref / conditions.vc_m_min) ** coeffs.vc_exponent
    return fc, coeffs.feed_ratio * fc, coeffs.passive_ratio * fc


def force_on_tool(components: tuple[float, float, float], direction_xz: np.ndarray) -> np.ndarray:
    """Force of the workpiece on the tool, (K, 3) N in the machine frame (X, Y, Z), for cuts along ``direction_xz``.

    components : (Fc, Ff, Fp) N.  direction_xz : (K, 2) float, the tool's direction of motion (X, Z), any length > 0.
    See the module docstring for the directions.
    """
    fc, ff, fp = components
    d = np.asarray(direction_xz, dtype=float).reshape(-1, 2)
    length = np.linalg.norm(d, axis=1)
    if np.any(length <= 0.0):
        raise ValueError("a cut needs a direction of motion in the XZ plane")
    d = d / length[:, None]
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)  # a normal to d in the XZ plane
    side = n[:, 0] + n[:, 1]
    flip = (side < 0.0) | ((side == 0.0) & (n[:, 0] < 0.0))
    n[flip] *= -1.0
    f_xz = -ff * d + fp * n
    out = np.zeros((d.shape[0], 3))
    out[:, 0], out[:, 1], out[:, 2] = f_xz[:, 0], fc, f_xz[:, 1]
    return out
