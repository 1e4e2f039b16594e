"""Flyers: measured points that are not measurements of the surface (a probe's mis-trigger, dirt, a chip), set apart
before the deviations are fitted, the same way wherever a cloud is fitted (``inspect --identify``'s identification,
``diagnose``).

    screen = screen_flyers(points, normals, deviation_um)      # normals may be None
    kept = screen.keep                                          # (N,) bool

Two rules, in order:

1. the gate: a point whose deviation exceeds ``GATE_MM`` (the inspection's gate: beyond it a point belongs to no
   feature of the part) is set apart;
2. the local screen, for the points within the gate: a point whose deviation differs from the deviation of all but
   ``ALIKE`` of its ``NEIGHBOURS`` nearest neighbours on the surface by more than ``LOCAL_K`` robust sigmas of the
   local differences (and by more than ``LOCAL_FLOOR_UM``), all of them on one side of it, is a flyer (up to ``ALIKE``
   flyers side by side are found: a QA cloud's random flyers held two such pairs). The robust sigma is 1.4826 x the
   MAD of each point's deviation minus the median of its neighbours' (the local scatter: the probe noise, with the
   smooth part of any machine effect cancelled). Departing from nearly every neighbour, not from their median, keeps
   the points on either side of a step of the surface (a backlash reversal, a pass boundary): each has neighbours on
   its own side; and a flyer lies beyond its surroundings, not between them (a point in a narrow transition between
   two levels: 30 such points of a noise-free cone with backlash on X and Y were set apart without this).
   The screen is repeated on the points kept (a cluster of flyers) at most ``LOCAL_ROUNDS`` times. Where the
   surface each point is measured against is known (inspect), the neighbours are those on the same surface, and a
   surface with fewer than 2 ``NEIGHBOURS`` points (a datum face's few probe points) is not screened.

With Gaussian noise a point is set apart by rule 2 only when its own noise exceeds about ``LOCAL_K`` sigma on the
side away from nearly all its neighbours (far below one point in a million); 20 um flyers on a 1 um-noise cloud are
found, and no point of clean 1 um-noise cones cut with backlash (1 to 10 um, X, Y, B), servo lag, drift, error motions,
force, wear or clamping (a QA pass's clouds, 600 and 3000 points) is set apart.
The neighbours are found where the points lie on the surface (their deviation along the normal taken out, when the
normals are known), so a flyer's own offset does not change them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The inspection's gate, mm: a point farther than this from the nominal surface belongs to no feature.
GATE_MM = 0.5
#: More than this share of a cloud's points beyond the gate: not flyers but a cloud of another cut, frame or unit;
#: refused by ``inspect`` and ``diagnose`` alike (a cone turned 180 deg about Z, 64.9 % beyond, was inspected with a
#: half angle error of +3498 urad as its figure, a QA pass).
MAX_BEYOND_GATE = 0.1
#: The local screen's neighbours (on the surface), its threshold in robust sigmas and its floor (um).
NEIGHBOURS = 8
ALIKE = 2
LOCAL_K = 8.0
LOCAL_FLOOR_UM = 2.0
LOCAL_ROUNDS = 3


@dataclass(frozen=True)
class FlyerScreen:
    """What the screen set apart. keep : (N,) bool, the points kept. beyond_gate / local : (N,) bool, the points set
    apart by the gate and by the local screen. local_sigma_um : the robust sigma of the local differences (um) the
    local screen used (nan with too few points)."""

    keep: np.ndarray
    beyond_gate: np.ndarray
    local: np.ndarray
    deviation_um: np.ndarray
    local_sigma_um: float
    gate_mm: float = GATE_MM

    @property
    def n_apart(self) -> int:
        return int((~self.keep).sum())

    def as_dict(self) -> dict:
        """The report's entry: the rule, how many were set apart by each part of it, and the largest deviation."""
        d = self.deviation_um

        def largest(mask):
            return float(d[mask][np.argmax(np.abs(d[mask]))]) if mask.any() else None

        return {"points": int(self.keep.size), "set_apart": self.n_apart,
                "beyond_gate": int(self.beyond_gate.sum()), "beyond_gate_largest_um": largest(self.beyond_gate),
                "local": int(self.local.sum()), "local_largest_um": largest(self.local),
                "local_sigma_um": self.local_sigma_um, "rule": rule_text(self.gate_mm)}

    def sentence(self, what: str = "the fit") -> str | None:
        """One line for the terminal and the reports, or None when nothing was set apart."""
        if not self.n_apart:
            return None
        parts = []
        info = self.as_dict()
        if info["beyond_gate"]:
            parts.append(f"{info['beyond_gate']} beyond the {self.gate_mm:g} mm gate (largest "
                         f"{info['beyond_gate_largest_um']:+.0f} um)")
        if info["local"]:
            parts.append(f"{info['local']} within the gate departing from nearly every neighbour by more than "
                         f"{LOCAL_K:g} robust sigma of the local differences ({self.local_sigma_um:.2f} um; largest "
                         f"{info['local_largest_um']:+.1f} um)")
        return (f"{self.n_apart} of {self.keep.size} points set apart as flyers and left out of {what}: "
                f"{'; '.join(parts)}")


# The local differences' sigma over the probe noise's, for Gaussian noise: a point less the median of its NEIGHBOURS
# (8) neighbours has variance sigma^2 (1 + pi / (2 x 8)) (the median's asymptotic variance), a factor sqrt(1.196).
LOCAL_TO_NOISE = math.sqrt(1.0 + math.pi / (2.0 * NEIGHBOURS))
#: A residual above this multiple of the cloud's own noise is a part the fitted model does not explain.
UNEXPLAINED_FACTOR = 1.5
#: A cloud whose own noise is below this (um) has none a probe would give: a simulation without probe noise.
NOISE_FREE_UM = 0.01


def residual_above_noise_note(residual_um: float, local_sigma_um: float, what: str = "the identification",
                              kept=(), setup_given: bool = False) -> str | None:
    """A sentence when a fit's residual RMS (um) stays above ``UNEXPLAINED_FACTOR`` x the cloud's own noise, read from
    neighbouring points (``local_sigma_um`` / ``LOCAL_TO_NOISE``: independent of any model); else None. ``kept``: the
    parameters the fit held at the twin's values although the part sees them (not significant: this part cannot
    determine them, from its set-up or from each other), a second cause of such a residual, named with the first.
    ``setup_given``: the set-up's accuracy was given, or a best fit took the set-up (the note then names only a second
    placement)."""
    noise = local_sigma_um / LOCAL_TO_NOISE
    if math.isfinite(noise) and noise < NOISE_FREE_UM:
        # (a QA pass: a noise-free virtual-shop cloud was refused as driven by "a backlash, a servo lag", the true
        # machine having neither: against no noise, the first-order model's own residual reads as effects)
        return (f"the cloud shows no probe noise ({noise:.3f} um between neighbouring points): a simulation without "
                f"it? {what[0].upper() + what[1:]} judges each change against the noise, and against none the "
                f"first-order model's own residual ({residual_um:.2f} um RMS) reads as effects; give the virtual "
                "CMM a probe noise (simulate --noise-um, e.g. 0.5)")
    if not (math.isfinite(noise) and noise > 0 and residual_um > UNEXPLAINED_FACTOR * noise):
        return None
    head = (f"{what} leaves {residual_um:.2f} um RMS, above the cloud's own noise ({noise:.2f} um, from neighbouring "
            "points)")
    if not kept:
        return (f"{head}: the part holds an effect the twin's parameters do not describe; `trueaxis diagnose` looks for "
                "it")
    names = ", ".join(list(kept)[:6]) + (" ..." if len(kept) > 6 else "")
    how = ("a second placement of the part separates them" if setup_given else
           "a second placement of the part, or the set-up's accuracy given with --setup-sigma-um, separates them")
    return (f"{head}: either the part holds an effect the twin's parameters do not describe (`trueaxis diagnose` looks "
            f"for it), or changes of the parameters kept ({names}) that this part cannot determine, from its set-up "
            f"or from each other ({how})")


def rule_text(gate_mm: float = GATE_MM) -> str:
    return (f"beyond the {gate_mm:g} mm gate; or within it, a deviation that differs from each of its {NEIGHBOURS} "
            f"nearest neighbours' on the surface but {ALIKE}, all on one side, by more than {LOCAL_K:g} x 1.4826 MAD "
            f"of (deviation - median of the neighbours') and more than {LOCAL_FLOOR_UM:g} um")


def _neighbour_values(where: np.ndarray, d: np.ndarray, idx: np.ndarray, k: int) -> np.ndarray:
    """(len(idx), k) the deviations of each point's k - 1 nearest neighbours among ``idx`` (NaN: the point itself)."""
    from scipy.spatial import cKDTree

    _, nb = cKDTree(where[idx]).query(where[idx], k=k)
    dv = d[idx]
    own = np.arange(idx.size)[:, None]
    others = np.where(nb == own, -1, nb)  # the point itself (not always first: a duplicate point)
    return np.where(others >= 0, dv[np.maximum(others, 0)], np.nan)


def _local_round(where: np.ndarray, d: np.ndarray, idx: np.ndarray, surface=None) -> tuple[np.ndarray, float]:
    """(flagged (len(idx),) bool, sigma um) over the points ``idx`` (one round of rule 2); ``surface`` (N,) labels:
    neighbours on the same surface only, and a surface with fewer than 2 NEIGHBOURS points (a datum face's few
    probe points) not screened: its nearest points lie on another surface, whose deviation is another's (a QA pass:
    exact datum points flagged against the cone's)."""
    k = min(NEIGHBOURS + 1, idx.size)
    groups = [np.arange(idx.size)] if surface is None else \
        [g for g in (np.flatnonzero(surface[idx] == s) for s in np.unique(surface[idx])) if g.size >= 2 * NEIGHBOURS]
    vals = np.full((idx.size, k), np.nan)
    screened = np.zeros(idx.size, bool)
    for g in groups:
        vals[g] = _neighbour_values(where, d, idx[g], k)
        screened[g] = True
    dv = d[idx]
    local = (dv[screened] - np.nanmedian(vals[screened], axis=1)) if screened.any() else np.zeros(0)
    sigma = float(1.4826 * np.median(np.abs(local - np.median(local)))) if local.size else float("nan")
    diff = vals - dv[:, None]  # the neighbours' deviations relative to the point's (nan: the point itself)
    order = np.argsort(np.abs(diff), axis=1)  # nan sorts last
    rest = np.take_along_axis(diff, order, axis=1)[:, ALIKE:k - 1]  # all but the ALIKE nearest in value
    one_side = np.all(rest > 0, axis=1) | np.all(rest < 0, axis=1)
    return screened & one_side & (np.min(np.abs(rest), axis=1) > max(LOCAL_K * sigma, LOCAL_FLOOR_UM)), sigma


def screen_flyers(points, normals, deviation_um, gate_mm: float = GATE_MM, surface=None) -> FlyerScreen:
    """The flyers of a measured cloud (module docstring). points (N, 3) mm; normals (N, 3) unit or None;
    deviation_um (N,) the deviation each point is fitted with (from the nominal surface, or from the twin's);
    surface (N,) the surface each point is measured against, or None (neighbours on any)."""
    pts = np.asarray(points, float)
    d = np.asarray(deviation_um, float)
    surface = None if surface is None else np.asarray(surface)
    beyond = ~(np.abs(d) <= gate_mm * 1000.0)  # a non-finite deviation is beyond any gate
    where = pts if normals is None else pts - (np.where(beyond, 0.0, d) / 1000.0)[:, None] * np.asarray(normals)
    local = np.zeros(d.size, bool)
    sigma = float("nan")
    for _ in range(LOCAL_ROUNDS):
        idx = np.flatnonzero(~beyond & ~local)
        if idx.size < 2 * NEIGHBOURS:
            break
        flagged, s = _local_round(where, d, idx, surface)
        sigma = s if np.isnan(sigma) else sigma
        if not flagged.any():
            break
        local[idx[flagged]] = True
    return FlyerScreen(~beyond & ~local, beyond, local, d, sigma, gate_mm)
