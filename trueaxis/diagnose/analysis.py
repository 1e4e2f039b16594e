"""Where the gap lies, which candidate explains it, and how far it shrinks (DESIGN §8), on arrays.

Held-out judgement. Every fit is cross-validated over K folds whose members are kept apart from their neighbours:
``region`` folds are cells of a coarse grid on the part (each cell whole in one fold), ``time`` folds are contiguous
blocks of cut time, ``random`` folds are random points. Each point's held-out prediction comes from the fit on the
other folds, so "before" and "after" figures are on points no fit has seen.

Significance against the probe noise. With held-out squared gaps g_i^2 and held-out squared residuals r_i^2, the
candidate's gain per point is d_i = g_i^2 - r_i^2. A candidate explains the gap when the mean gain is both
significant (mean / standard error > ``Z_MIN``; a paired test on held-out points, which needs no distribution of
the fit's parameters) and material (more than ``MIN_GAIN_OF_NOISE`` sigma^2). The noise sigma is given or estimated
from the data: the differences of the gap between nearest neighbours on the part that were cut close in time carry
twice the noise variance and almost none of any smooth effect (robust MAD scale). An F-test of the training fit is
reported too.

Bounded fits. Every fit, the held-out ones included, keeps the parameters inside the candidates' plausible bounds
(``lsq_linear`` when the free solution leaves them), so a candidate is judged by what it explains with physically
plausible values; a fit that wanted to leave its bounds is flagged not plausible -- except for bounds that are the
candidate's form (``Candidate.form``: the non-negative weights of servo lag's mixture of loops, whose nearly
collinear columns a free fit may weight with opposite signs).

Choice and ambiguity. Candidates are ranked by held-out gain. Tied with the best are those whose gain is at least
``TIE`` of its gain or not significantly below it (paired held-out z of the deficit < ``Z_TIE``). A tied candidate is
dropped when the fitted values of another tied one show a physical signature it cannot produce (``ruled_out``: a
machine compliance significantly different in X and Y while the tool stands along machine Z, which a round tool's
bending cannot give). Among the remaining tied ones the plausible, then a new effect rather than a re-identification
of the twin, then fewer parameters is preferred (parsimony, plausibility), and the others are reported as
indistinguishable on this part (``Diagnosis.tied``, with the measurement that would separate them).

Two effects against one (a nested test). All pairs of the ``PAIR_POOL`` leading significant candidates are fitted; a
pair is kept only when its held-out gain over the best single candidate is significant at the stricter ``Z_PAIR``
(up to fifteen pairs are tried, and a strong effect's residual of form is structured, so a plain ``Z_MIN`` lets a
second candidate nibble at it) and material (more than ``MIN_GAIN_OF_NOISE`` sigma^2 and ``PAIR_MIN_SHARE`` of that
candidate's gain). The kept pairs compete with the same tie rule.

Confidence: 0.3 + 0.7 min(1, separation / 0.5), separation = 1 - (runner-up's gain / chosen's gain), at most
1 / (1 + k) when k candidates are tied with the chosen ones, halved when fitted values wanted to leave their bounds.
Candidates whose gain is at least ``ALMOST`` of the chosen's, and the tied ones, are listed as alternatives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.spatial import cKDTree

from .candidates import Candidate
from .state import TwinState

K_FOLDS = 5
Z_MIN = 4.0
MIN_GAIN_OF_NOISE = 0.1
ALMOST = 0.9
TIE = 0.97
Z_TIE = 2.0
PAIR_POOL = 6
PAIR_MIN_SHARE = 0.05
Z_PAIR = 5.0
Z_SIGNATURE = 4.0

SEPARATING_MEASUREMENT = {
    frozenset({"force_deflection", "tool_deflection"}): "a cut with a different tool stick-out or radial engagement "
    "(tool bending grows with the cube of the stick-out, machine compliance does not), or the slot block",
    frozenset({"servo_lag", "backlash"}): "the same part at a different feed: servo lag scales with the feed, "
    "backlash does not",
    frozenset({"thermal", "twin_parameters"}): "the same cut repeated after a warm-up or at another time: drift "
    "changes with time, location errors do not",
    frozenset({"thermal", "backlash"}): "the passes cut in the reverse order or direction: a reversal step follows "
    "the direction, a drift follows the time",
    frozenset({"force_deflection", "twin_parameters"}): "a second placement of the part on the table, or a different "
    "feed per tooth (force scales with the feed, location errors do not)",
    frozenset({"tool_deflection", "twin_parameters"}): "a second placement of the part, or a different feed per tooth",
    frozenset({"force_deflection", "thermal"}): "a different feed per tooth: force scales with it, drift does not",
    frozenset({"tool_deflection", "thermal"}): "a different feed per tooth: force scales with it, drift does not",
    frozenset({"rotary_periodic", "twin_parameters"}): "a second placement of the part off the rotary axis: "
    "angular errors scale with the radius, location offsets do not",
}


def family(name: str) -> str:
    for f in ("backlash", "thermal", "rotary_periodic"):
        if name.startswith(f):
            return f
    return name


def separating_measurement(a: str, b: str) -> str:
    fa, fb = family(a), family(b)
    if fa == fb:
        return f"a second placement or the slot block, which move {a} and {b} differently"
    return SEPARATING_MEASUREMENT.get(frozenset({fa, fb}),
                                      "a second placement of the part, the slot block, or a different feed")


# -------------------------------------------------------------------------------------------------- the folds ----
def make_folds(state: TwinState, split: str = "region", k: int = K_FOLDS, seed: int = 0) -> np.ndarray:
    """(N,) fold index 0..k-1 of every point (see the module docstring)."""
    rng = np.random.default_rng(seed)
    n = len(state)
    if split == "random":
        return rng.permutation(np.arange(n) % k)
    if split == "time":
        blocks = 4 * k
        order = np.argsort(state.t_s, kind="stable")
        block = np.empty(n, int)
        block[order] = np.arange(n) * blocks // n
    elif split == "region":
        p = state.points - state.points.mean(axis=0)
        # Cells of a grid along the cloud's principal directions, about 4k of them over the part.
        _, _, vt = np.linalg.svd(p, full_matrices=False)
        c = p @ vt.T
        ext = np.ptp(c, axis=0)
        dims = ext > 0.05 * ext.max()
        per = max(2, int(round((4 * k) ** (1 / max(1, dims.sum())))))
        cell = np.zeros(n, int)
        for d in np.nonzero(dims)[0]:
            b = np.minimum(((c[:, d] - c[:, d].min()) / max(ext[d], 1e-12) * per).astype(int), per - 1)
            cell = cell * per + b
        _, block = np.unique(cell, return_inverse=True)
    else:
        raise ValueError(f"split must be region, time or random, got {split!r}")
    nb = block.max() + 1
    # Assign blocks to folds so that the folds hold about equal numbers of points.
    sizes = np.bincount(block, minlength=nb)
    fold_of_block = np.empty(nb, int)
    load = np.zeros(k)
    perm = rng.permutation(nb)
    for b in perm[np.argsort(-sizes[perm], kind="stable")]:
        f = int(np.argmin(load))
        fold_of_block[b] = f
        load[f] += sizes[b]
    return fold_of_block[block]


# ------------------------------------------------------------------------------------------------- the noise ----
def estimate_noise_um(state: TwinState) -> float:
    """Probe noise sigma (um) from nearest-neighbour differences of the gap (see the module docstring)."""
    g = state.gap_um
    if g.size < 10:
        return float(np.std(g))
    tree = cKDTree(state.points)
    dist, idx = tree.query(state.points, k=min(6, g.size))
    # The nearest neighbour cut within a short time (same pass, same direction): a smooth effect cancels.
    dt = np.abs(state.t_s[idx[:, 1:]] - state.t_s[:, None])
    tol = max(0.01 * state.t_end_s, 0.5)
    ok = dt < tol
    j = np.where(ok.any(axis=1), ok.argmax(axis=1), 0)
    pair = idx[np.arange(g.size), 1 + j]
    keep = ok.any(axis=1)
    d = (g - g[pair])[keep] if keep.sum() >= 10 else g - g[idx[:, 1]]
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / math.sqrt(2.0))


# ---------------------------------------------------------------------------------------------- the fitting ----
def _solve(S, g, rcond=1e-4):
    """Least squares with column scaling; returns theta (p,) and the pseudo-inverse normal matrix (p, p)."""
    scale = np.sqrt(np.mean(S**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    A = S / scale
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > rcond * s[0] if s.size else s
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    theta = (Vt.T * inv) @ (U.T @ g) / scale
    cov_unit = (Vt.T * inv**2) @ Vt / np.outer(scale, scale)
    return theta, cov_unit, int(keep.sum())


@dataclass
class Fit:
    """A candidate (or a pair) fitted and judged on held-out points.

    name : "a" or "a+b".  parameters, units : names.  value, std : fitted on all points (std from the residual
    scatter).  held_out_pred_um : (N,) cross-validated prediction.  gain_um2 : mean held-out g^2 - r^2.
    z : paired significance of the gain.  f_stat, f_p : F-test of the fit on all points.
    plausible : fitted values inside their bounds.  rank : effective number of parameters.
    """

    name: str
    members: list
    parameters: list
    units: list
    value: np.ndarray
    std: np.ndarray
    held_out_pred_um: np.ndarray
    gain_um2: float
    z: float
    f_stat: float
    f_p: float
    plausible: bool
    rank: int
    n_parameters: int
    rms_after_um: float = 0.0
    explained_share: float = 0.0
    significant: bool = False
    extra: dict = field(default_factory=dict)
    cov: np.ndarray | None = None

    def difference_z(self, a: str, b: str) -> float:
        """(value[a] - value[b]) / its standard deviation (with the covariance of the fit on all points)."""
        i, j = self.parameters.index(a), self.parameters.index(b)
        var = self.cov[i, i] + self.cov[j, j] - 2 * self.cov[i, j] if self.cov is not None else \
            self.std[i] ** 2 + self.std[j] ** 2
        return float((self.value[i] - self.value[j]) / max(math.sqrt(max(var, 0.0)), 1e-300))


def _solve_bounded(S, g, bounds):
    """Least squares within the plausible bounds (``lsq_linear``, column-scaled); the plain solution when it is
    inside them already. Returns theta (p,) and whether a bound is active."""
    theta, _, _ = _solve(S, g)
    lo = np.array([-np.inf if b is None else b[0] for b in bounds], float)
    hi = np.array([np.inf if b is None else b[1] for b in bounds], float)
    if np.all((theta >= lo) & (theta <= hi)):
        return theta, False
    from scipy.optimize import lsq_linear

    scale = np.sqrt(np.mean(S**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    r = lsq_linear(S / scale, g, bounds=(lo * scale, hi * scale), method="bvls", lsmr_tol="auto")
    return r.x / scale, True


def fit_candidate(cands: list[Candidate], g: np.ndarray, folds: np.ndarray, bounded: bool = True) -> Fit:
    """Fit the candidates' columns to the gap, cross-validated over ``folds``. ``bounded``: every fit (the held-out
    ones too) keeps the parameters inside their plausible bounds, so that a candidate is judged by what it explains
    with physically plausible values, not by what an absurd value of an aliased column can mimic (DESIGN §8: prefer
    bounded parameter changes)."""
    S = np.column_stack([c.columns for c in cands])
    n, p = S.shape
    bounds = [b for c in cands for b in (c.plausible or [None] * c.n_parameters)]
    pred = np.zeros(n)
    for f in np.unique(folds):
        tr = folds != f
        theta = _solve_bounded(S[tr], g[tr], bounds)[0] if bounded else _solve(S[tr], g[tr])[0]
        pred[~tr] = S[~tr] @ theta
    theta, cov_unit, rank = _solve(S, g)
    at_bound = False
    if bounded:
        theta_b, at_bound = _solve_bounded(S, g, bounds)
        if at_bound:
            theta = theta_b
    resid = g - S @ theta
    dof = max(n - rank, 1)
    s2 = float(resid @ resid) / dof
    std = np.sqrt(np.maximum(np.diag(cov_unit) * s2, 0.0))
    rss0, rss1 = float(g @ g), float(resid @ resid)
    f_stat = ((rss0 - rss1) / max(rank, 1)) / max(rss1 / dof, 1e-300)
    f_p = float(stats.f.sf(f_stat, max(rank, 1), dof))
    d = g**2 - (g - pred) ** 2
    gain = float(d.mean())
    z = gain / max(float(d.std(ddof=1)) / math.sqrt(n), 1e-300)
    # At a bound the unbounded fit wanted a value outside the plausible range: the candidate is stretched.
    theta_free = _solve(S, g)[0] if at_bound else theta
    form = [c.form_bound(i) for c in cands for i in range(c.n_parameters)]
    plausible = all(b is None or f or (b[0] <= v <= b[1]) for v, b, f in zip(theta_free, bounds, form))
    return Fit(name="+".join(c.name for c in cands), members=[c.name for c in cands],
               parameters=[x for c in cands for x in c.parameters], units=[x for c in cands for x in c.units],
               value=theta, std=std, held_out_pred_um=pred, gain_um2=gain, z=float(z), f_stat=float(f_stat), f_p=f_p,
               plausible=plausible, rank=rank, n_parameters=p, cov=cov_unit * s2)


def gap_figures(r: np.ndarray) -> dict:
    a = np.abs(r)
    return {"rms": float(np.sqrt(np.mean(r**2))), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


# ------------------------------------------------------------------------------------------------- where ----
def state_variables(state: TwinState) -> dict:
    """name -> (values (N,), kind "continuous" | "categorical", unit)."""
    out = {}
    for j, a in enumerate(state.axis_names):
        rot = a in state.rotary
        v = np.degrees(state.q[:, j]) if rot else state.q[:, j]
        out[f"{a} position"] = (v, "continuous", "deg" if rot else "mm")
    for j, a in enumerate(state.axis_names):
        out[f"{a} direction"] = (state.direction[:, j], "categorical", "sign")
    out["time since start"] = (state.t_s, "continuous", "s")
    out["feed"] = (state.feed_mm_min, "continuous", "mm/min")
    if state.has_force:
        out["cutting force"] = (np.linalg.norm(state.force_n, axis=1), "continuous", "N")
    out["height on tool"] = (state.height_mm, "continuous", "mm")
    return out


def _binned_predict(x_tr, g_tr, x_te, kind, bins=10):
    if kind == "categorical":
        cats = np.unique(x_tr)
        means = {c: g_tr[x_tr == c].mean() for c in cats}
        base = g_tr.mean()
        return np.array([means.get(v, base) for v in x_te])
    edges = np.unique(np.quantile(x_tr, np.linspace(0, 1, bins + 1)))
    if edges.size < 2:
        return np.full(x_te.shape, g_tr.mean())
    bt = np.clip(np.searchsorted(edges, x_tr, side="right") - 1, 0, edges.size - 2)
    sums = np.bincount(bt, g_tr, minlength=edges.size - 1)
    cnt = np.bincount(bt, minlength=edges.size - 1)
    means = np.where(cnt > 0, sums / np.maximum(cnt, 1), g_tr.mean())
    be = np.clip(np.searchsorted(edges, x_te, side="right") - 1, 0, edges.size - 2)
    return means[be]


def where(state: TwinState, folds: np.ndarray, noise_um: float) -> list[dict]:
    """Rank the state variables by the held-out R^2 of a binned-mean fit of the gap (1-D each)."""
    g = state.gap_um
    ss = float(np.sum((g - g.mean()) ** 2))
    out = []
    for name, (x, kind, unit) in state_variables(state).items():
        if np.ptp(x) <= 1e-9:
            out.append({"variable": name, "unit": unit, "held_out_r2": 0.0, "note": "constant while cutting"})
            continue
        pred = np.empty_like(g)
        for f in np.unique(folds):
            tr = folds != f
            pred[~tr] = _binned_predict(x[tr], g[tr], x[~tr], kind)
        r2 = 1.0 - float(np.sum((g - pred) ** 2)) / max(ss, 1e-300)
        out.append({"variable": name, "unit": unit, "held_out_r2": max(r2, 0.0)})
    out.sort(key=lambda d: -d["held_out_r2"])
    # The share of the gap's variance above the noise: what any variable could at most explain.
    ceiling = max(0.0, 1.0 - noise_um**2 * g.size / max(ss, 1e-300))
    for d in out:
        d["share_of_explainable"] = d["held_out_r2"] / ceiling if ceiling > 0 else 0.0
    return out


# ------------------------------------------------------------------------------------------------- which ----
@dataclass
class Diagnosis:
    noise_um: float
    noise_estimated: bool
    where: list
    fits: list
    chosen: list
    chosen_fit: Fit | None
    confidence: float
    alternatives: list
    separating_measurement: str | None
    verdict: str
    gap_before: dict
    gap_after: dict
    shrink_raw: float
    shrink_above_noise: float
    split: str
    skipped: list
    tied: dict = field(default_factory=dict)
    ruled_out: list = field(default_factory=list)


def tool_along_machine_z(state: TwinState, tol: float = 0.995) -> bool:
    """True when the tool axis lies along machine Z at every cut (a three-axis part, or a five-axis one cut with the
    head straight): machine X and Y then both lie in the plane in which a round tool bends."""
    from .candidates import _machine_direction

    return bool(np.all(np.abs(np.einsum("ij,ij->i", state.axis, _machine_direction(state, 2))) > tol))


def ruled_out(fit: Fit, tool_vertical: bool) -> dict:
    """{member of ``fit``: [candidates that cannot stand in for it]}: physical signatures in the fitted values that
    another candidate, however well it matches the gap's shape, cannot produce.

    - A machine compliance that differs significantly between X and Y (|c_X - c_Y| > ``Z_SIGNATURE`` standard
      deviations) while the tool lies along machine Z: a round tool bends equally in every direction normal to its
      axis, so tool deflection cannot be that anisotropic. (An isotropic fit proves nothing: the two stay tied.)"""
    out = {}
    if tool_vertical and "force_deflection" in fit.members and {"compliance_X", "compliance_Y"} <= set(fit.parameters):
        z = fit.difference_z("compliance_X", "compliance_Y")
        fit.extra["anisotropy_z"] = z
        if abs(z) > Z_SIGNATURE:
            out["force_deflection"] = ["tool_deflection"]
    return out


def _prefer(best: Fit, pool: list, g: np.ndarray, tool_vertical: bool = False, notes: list | None = None
            ) -> tuple[Fit, list]:
    """(the preferred fit, the others tied with it) among ``pool`` (``best`` has the largest held-out gain).

    Tied with the best: a gain of at least ``TIE`` of its gain, or a gain not significantly below it on the held-out
    points (paired z of the deficit < ``Z_TIE``). A tied fit that only swaps a member of another tied fit for a
    candidate that fit's values rule out (``ruled_out``: a physical signature it cannot produce) is dropped. Among
    the tied ones the plausible (fitted values inside their bounds), then the one that is a new effect rather than a
    re-identification of the twin, then the one with fewer parameters, then the larger gain is preferred."""
    tied = [best]
    for f in pool:
        if f is best:
            continue
        d = (g - f.held_out_pred_um) ** 2 - (g - best.held_out_pred_um) ** 2
        zz = float(d.mean()) / max(float(d.std(ddof=1)) / math.sqrt(g.size), 1e-300)
        if f.gain_um2 >= TIE * best.gain_um2 or zz < Z_TIE:
            tied.append(f)
    drop = set()
    for f in tied:
        for member, excluded in ruled_out(f, tool_vertical).items():
            rest = sorted(m for m in f.members if m != member)
            for h in tied:
                if h is not f and id(h) not in drop and any(sorted(h.members) == sorted(rest + [x])
                                                              for x in excluded):
                    drop.add(id(h))
                    h.extra["ruled_out_by"] = f.name
                    if notes is not None:
                        notes.append(f"{h.name} ruled out against {f.name}: the fitted machine compliance differs "
                                     f"between X and Y by {abs(f.extra['anisotropy_z']):.1f} standard deviations, "
                                     f"which a round tool's bending (equal in every direction normal to the tool) "
                                     f"cannot produce")
    tied = [f for f in tied if id(f) not in drop]
    tied.sort(key=lambda f: (not f.plausible, "twin_parameters" in f.members, f.n_parameters, -f.gain_um2))
    return tied[0], tied[1:]


def _significant(gain, z, noise_um):
    return z > Z_MIN and gain > MIN_GAIN_OF_NOISE * noise_um**2


def diagnose_state(state: TwinState, candidates: list[Candidate], *, split: str = "region",
                   noise_um: float | None = None, skipped=(), seed: int = 0) -> Diagnosis:
    """The whole judgement on one twin state and a built candidate list."""
    g = state.gap_um
    folds = make_folds(state, split, seed=seed)
    estimated = noise_um is None
    sigma = estimate_noise_um(state) if estimated else float(noise_um)
    fits = [fit_candidate([c], g, folds) for c in candidates]
    before = gap_figures(g)
    ms_before = float(np.mean(g**2))
    for f in fits:
        f.rms_after_um = float(np.sqrt(np.mean((g - f.held_out_pred_um) ** 2)))
        f.explained_share = f.gain_um2 / max(ms_before - sigma**2, 1e-12)
        f.significant = _significant(f.gain_um2, f.z, sigma)
    fits.sort(key=lambda f: -f.gain_um2)
    sig = [f for f in fits if f.significant]
    chosen_fit, alternatives, confidence, sep, tied, notes = None, [], 0.0, None, {}, []
    if sig:
        best = sig[0]
        vertical = tool_along_machine_z(state)
        chosen_fit, tie_fits = _prefer(best, sig, g, vertical, notes)
        # A second effect: every pair of the leading significant candidates (a pair need not contain the best single
        # one: one candidate with many columns can mimic two effects at once, and a second effect hidden under the
        # first need not be the runner-up alone). A pair is taken when it beats the best single candidate on held-out
        # points significantly (paired z > Z_PAIR: up to fifteen pairs are tried) and materially (by more than the
        # noise floor and PAIR_MIN_SHARE of that candidate's gain: the candidates' forms are poorer than the real
        # effects, and a strong effect leaves a residual of form that a second candidate can always nibble at).
        by_name = {c.name: c for c in candidates}
        top = [f.name for f in sig[:PAIR_POOL]]
        pairs = []
        for i, na in enumerate(top):
            for nb in top[i + 1:]:
                pair = fit_candidate([by_name[na], by_name[nb]], g, folds)
                d = (g - best.held_out_pred_um) ** 2 - (g - pair.held_out_pred_um) ** 2
                extra = float(d.mean())
                zz = extra / max(float(d.std(ddof=1)) / math.sqrt(g.size), 1e-300)
                if zz > Z_PAIR and extra > max(MIN_GAIN_OF_NOISE * sigma**2, PAIR_MIN_SHARE * best.gain_um2):
                    pair.z, pair.extra = zz, {"gain_over_single_um2": extra, "over": best.name}
                    pairs.append(pair)
        if pairs:
            pairs.sort(key=lambda f: -f.gain_um2)
            for pf in pairs:
                pf.rms_after_um = float(np.sqrt(np.mean((g - pf.held_out_pred_um) ** 2)))
                pf.explained_share = pf.gain_um2 / max(ms_before - sigma**2, 1e-12)
                pf.significant = True
            chosen_fit, tie_fits = _prefer(pairs[0], pairs, g, vertical, notes)
            rivals = [f for f in pairs if f is not chosen_fit and "ruled_out_by" not in f.extra]
            # Each member's ties: the candidates that can replace it in a pair tied with the chosen one.
            for m in chosen_fit.members:
                other = [x for x in chosen_fit.members if x != m]
                tied[m] = [n for f in tie_fits for n in f.members
                           if set(other) <= set(f.members) and n not in chosen_fit.members]
        else:
            rivals = [f for f in sig if f is not chosen_fit and "ruled_out_by" not in f.extra]
            tied[chosen_fit.name] = [f.name for f in tie_fits]
        runner = rivals[0] if rivals else None
        alternatives = [f.name for f in sig if f.name not in chosen_fit.members
                        and (f.gain_um2 >= ALMOST * chosen_fit.gain_um2 or any(f.name in t for t in tied.values()))]
        separation = 1.0 if runner is None else max(0.0, 1.0 - runner.gain_um2 / max(chosen_fit.gain_um2, 1e-300))
        confidence = 0.3 + 0.7 * min(1.0, separation / 0.5)
        n_tied = sum(len(t) for t in tied.values())
        if n_tied:
            # k candidates explain the gap equally well here: at most one chance in k + 1 that the preferred one is
            # the right one, whatever the (tiny) margin says.
            confidence = min(confidence, 1.0 / (1 + n_tied))
        if not chosen_fit.plausible:
            confidence *= 0.5
        seps = [separating_measurement(m, t[0]) for m, t in tied.items() if t]
        if not seps and runner is not None and runner.gain_um2 >= ALMOST * chosen_fit.gain_um2:
            odd = [n for n in runner.members if n not in chosen_fit.members] or runner.members
            mine = [n for n in chosen_fit.members if n not in runner.members] or chosen_fit.members
            seps = [separating_measurement(mine[0], odd[0])]
        sep = "; ".join(dict.fromkeys(seps)) if seps else None
        after_r = g - chosen_fit.held_out_pred_um
        verdict = " + ".join(m + (f" (or {' / '.join(tied[m])}: indistinguishable on this part)" if tied.get(m) else "")
                             for m in chosen_fit.members)
    else:
        after_r = g
        verdict = "none of the candidates"
        best_z = fits[0].z if fits else 0.0
        confidence = float(min(0.99, 0.5 + 0.5 * (1.0 - max(0.0, best_z) / Z_MIN)))
    after = gap_figures(after_r)
    shrink_raw = 1.0 - after["rms"] / max(before["rms"], 1e-300)
    den = before["rms"] ** 2 - sigma**2
    shrink_noise = 1.0 - (after["rms"] ** 2 - sigma**2) / den if den > 0 else 0.0
    return Diagnosis(sigma, estimated, where(state, folds, sigma), fits,
                     [] if chosen_fit is None else chosen_fit.members, chosen_fit, float(round(confidence, 3)),
                     alternatives, sep, verdict, before, after, float(shrink_raw), float(shrink_noise), split,
                     list(skipped), tied, list(dict.fromkeys(notes)))
