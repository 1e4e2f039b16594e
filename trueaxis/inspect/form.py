"""Form evaluation of measured features: circles (2D and in space), roundness, cones, cylinders, spheres, planes,
lines, straightness, parallelism; least-squares (Gauss) and minimum-zone (Chebyshev) associations.

Pure numpy/scipy, vectorised over the points; lengths in mm, angles in rad. Each function names the reference
feature it computes (ISO 12181 for roundness, ISO 12780 for straightness, ISO 1101 for parallelism) and the method.
Inputs are checked once at the door (shape, finiteness, enough points) with a ``ValueError``.

Sign conventions: radial and surface deviations are positive outward (material side away from the axis/centre);
plane normals and line directions are unit vectors, oriented so that their largest-magnitude component is positive
(a deterministic choice; fits carry no physical sign).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kernels import cone_normal_equations

__all__ = [
    "CircleFit", "ZoneCircle", "ConeFit", "PlaneFit", "LineFit",
    "fit_circle_least_squares", "minimum_zone_circle", "roundness",
    "fit_cone", "cone_error_amplification", "section_ring", "fit_plane", "fit_line", "straightness", "parallelism",
    "SphereFit", "ZoneSphere", "fit_sphere", "minimum_zone_sphere", "ZonePlane", "minimum_zone_plane",
    "CylinderFit", "ZoneCylinder", "fit_cylinder", "minimum_zone_cylinder", "Circle3DFit", "fit_circle_3d",
]


# ------------------------------------------------------------------------------------------------------------ checks

def _points(points, dims: tuple[int, ...], minimum: int, name: str = "points") -> np.ndarray:
    """The door: an (n, d) finite float64 array with d in dims and n >= minimum, or a clear ValueError."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] not in dims:
        shapes = " or ".join(f"(n, {d})" for d in dims)
        raise ValueError(f"{name} must have shape {shapes}, got {array.shape}")
    if len(array) < minimum:
        raise ValueError(f"{name} needs at least {minimum} points, got {len(array)}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def _unit(vector, name: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=np.float64).reshape(-1)
    norm = np.linalg.norm(vector)
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{name} must be a finite, non-zero vector, got {vector}")
    return vector / norm


def _orient(vector: np.ndarray) -> np.ndarray:
    """Flip a direction so that its largest-magnitude component is positive (deterministic sign for fits)."""
    return vector if vector[np.argmax(np.abs(vector))] >= 0 else -vector


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors e1, e2 with (e1, e2, axis) right-handed and orthonormal."""
    helper = np.eye(3)[np.argmin(np.abs(axis))]  # the world axis least parallel to `axis`: well conditioned
    e1 = np.cross(helper, axis)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


# ---------------------------------------------------------------------------------------- nonlinear least squares

def _normal_equations_of(residuals, jacobian):
    """``normal_equations(params) -> (J^T J, J^T f, f, f . f)`` from a residual function and its Jacobian."""

    def normal_equations(params):
        f, jac = residuals(params), jacobian(params)
        return jac.T @ jac, jac.T @ f, f, float(f @ f)

    return normal_equations


def _levenberg_marquardt(params, normal_equations, max_evaluations: int = 2000):
    """Minimise sum f^2 by Levenberg-Marquardt (Marquardt 1963; More, "The Levenberg-Marquardt algorithm:
    implementation and theory", 1978): each step solves (J^T J + lambda D) d = -J^T f, D the diagonal of J^T J
    (scale invariance), lambda lowered tenfold after a step that lowers the sum and raised tenfold after one that does
    not. Stops when a step changes the parameters by less than 1e-15 of their size (after scaling by D), when an
    accepted step lowers the sum by less than 1e-15 of it and promised no more, or after ``max_evaluations``.

    Why not scipy's ``least_squares``: importing scipy.optimize costs ``inspect`` 0.45 s, more than every fit of a
    million-point cone together, and the fits here are small (3 to 6 parameters, their Jacobians exact and
    well scaled), where the normal equations of a compiled pass (:func:`_cone_model`) are what makes them fast.

    params : (k,) float start. normal_equations(params) -> (J^T J (k, k), J^T f (k,), f (n,), sum f^2).
    Returns (params, J^T J, f, sum f^2) at the solution.
    """
    params = np.asarray(params, dtype=np.float64)
    normal, gradient, f, cost = normal_equations(params)
    damping = 1e-3
    evaluations = 1
    while evaluations < max_evaluations and cost > 0.0:
        scale = np.sqrt(np.diag(normal))
        scale[scale == 0] = 1.0
        scaled = normal / np.outer(scale, scale)
        try:
            step = -np.linalg.solve(scaled + damping * np.eye(len(params)), gradient / scale) / scale
        except np.linalg.LinAlgError:
            damping *= 10.0
            if damping > 1e16:
                break
            continue
        if np.linalg.norm(step * scale) <= 1e-15 * max(np.linalg.norm(params * scale), 1e-300):
            break  # the step is below the parameters' rounding
        promised = -float(2.0 * gradient @ step + step @ normal @ step)
        trial = params + step
        normal_new, gradient_new, f_new, cost_new = normal_equations(trial)
        evaluations += 1
        if cost_new < cost:
            small = cost - cost_new <= 1e-15 * cost and promised <= 1e-15 * cost
            params, normal, gradient, f, cost = trial, normal_new, gradient_new, f_new, cost_new
            damping = max(damping / 10.0, 1e-15)
            if small:
                break
        else:
            damping *= 10.0
            if damping > 1e16:
                break
    return params, normal, f, cost


# ----------------------------------------------------------------------------------------------------------- circles

@dataclass(frozen=True)
class CircleFit:
    """Least-squares reference circle (ISO 12181-2 LSCI).

    center : (2,) float, mm
    radius : float, mm
    residuals : (n,) float, mm, radial deviation |p - center| - radius of each point, positive outward
    """

    center: np.ndarray
    radius: float
    residuals: np.ndarray


@dataclass(frozen=True)
class ZoneCircle:
    """Minimum-zone reference circles (ISO 12181-2 MZCI): two concentric circles enclosing the profile, of least
    radial separation.

    center : (2,) float, mm
    radius_inner, radius_outer : float, mm
    width : float, mm, radius_outer - radius_inner = the minimum-zone roundness
    residuals : (n,) float, mm, |p - center| - (radius_inner + radius_outer) / 2
    """

    center: np.ndarray
    radius_inner: float
    radius_outer: float
    width: float
    residuals: np.ndarray


def fit_circle_least_squares(points2d) -> CircleFit:
    """Least-squares circle: minimise the sum of squared radial (geometric) distances.

    Method: the algebraic fit of Kasa (1976, IEEE Trans. Instrum. Meas. IM-25, "A circle fitting procedure and its
    error analysis"), x^2 + y^2 = 2 a x + 2 b y + c solved as a linear least-squares problem, gives the start; a
    Levenberg-Marquardt refinement (:func:`_levenberg_marquardt`) of the geometric residuals |p - c| - R with their exact
    Jacobian gives the ISO 12181-2 least-squares reference circle (Gauss-Newton on the geometric distance, as in
    ISO/TS 12181-2 and Forbes, NPL DITC 140/89).

    Parameters
    ----------
    points2d : (n, 2) float, mm, n >= 3, not all on one line

    Returns
    -------
    CircleFit
    """
    points2d = _points(points2d, (2,), 3, "points2d")
    # work about the centroid, scaled to unit size, so the normal equations are well conditioned
    origin = points2d.mean(axis=0)
    local = points2d - origin
    scale = np.sqrt((local ** 2).sum(axis=1).mean())
    if scale == 0.0:
        raise ValueError("points2d are all the same point")
    local = local / scale
    design = np.column_stack([2.0 * local, np.ones(len(local))])
    solution, _, rank, singular = np.linalg.lstsq(design, (local ** 2).sum(axis=1), rcond=None)
    if rank < 3 or singular[-1] < 1e-9 * singular[0]:
        raise ValueError("points2d lie on a line: no circle through them")
    center0 = solution[:2]
    radius0 = np.sqrt(solution[2] + center0 @ center0)

    def residuals(params):
        return np.hypot(*(local - params[:2]).T) - params[2]

    def jacobian(params):
        # d(|p - c| - R)/dc = -(p - c)/|p - c|, d/dR = -1
        delta = local - params[:2]
        distance = np.hypot(*delta.T)[:, None]
        return np.column_stack([-delta / distance, -np.ones(len(delta))])

    solution = _levenberg_marquardt(np.r_[center0, radius0], _normal_equations_of(residuals, jacobian))[0]
    center = origin + solution[:2] * scale
    radius = float(solution[2] * scale)
    return CircleFit(center=center, radius=radius, residuals=np.hypot(*(points2d - center).T) - radius)


def minimum_zone_circle(points2d, start: np.ndarray | None = None, max_iterations: int = 300) -> ZoneCircle:
    """Minimum-zone circles: the centre c minimising max_i |p_i - c| - min_i |p_i - c| (ISO 12181-2 MZCI).

    Method: sequential linear programming with a trust region (the linearised Chebyshev problem of Dhanish & Shunmugam,
    Precision Engineering 13 (1991), "An algorithm for form error evaluation using the theory of discrete and linear
    Chebyshev approximation"), :func:`_chebyshev_zone`. About the current centre c the radii are
    r_i(c + d) ~ r_i - u_i . d, u_i the unit vector from c to p_i; the linear program

        minimise  a - b   over (d, a, b)   subject to   b <= r_i - u_i . d <= a,   |d|_inf <= trust radius

    gives a step; it is accepted when the exact zone width decreases, and the trust radius grows or shrinks with the
    ratio of actual to predicted decrease. The linearisation error is |d|^2 / (2 r), so near the solution the steps
    converge like Newton steps (the optimum is a vertex: 2 outer and 2 inner contact points, generically). Only the
    points of largest and smallest radius can be contacts: each linear program holds those (a few thousand, found in
    O(n)), with the step capped so that no other point can reach the zone's edges; the exact width over all points
    decides each step. Starts from the least-squares centre (of an evenly strided sample of 20,000 points for a larger
    profile), which is within a zone width of the minimum-zone centre for a roundness profile. The problem is not
    convex in general: for a profile far from a circle (a partial arc of a few degrees, a random scatter) this is a
    local minimum near the least-squares centre.

    Parameters
    ----------
    points2d : (n, 2) float, mm, n >= 4 spread around a centre
    start : (2,) float, mm, optional start centre (default: the least-squares centre)
    max_iterations : int, linear programs solved at most

    Returns
    -------
    ZoneCircle
    """
    points2d = _points(points2d, (2,), 4, "points2d")
    if start is None:
        start = fit_circle_least_squares(points2d[::max(1, -(-len(points2d) // 20_000))]).center
    center0 = np.asarray(start, dtype=np.float64).reshape(2)
    radii0 = np.hypot(*(points2d - center0).T)
    step = max(float(np.ptp(radii0)), 1e-12 * float(radii0.mean()))

    def distance(c):
        return np.hypot(points2d[:, 0] - c[0], points2d[:, 1] - c[1])

    def jacobian(c, index):
        delta = points2d[index] - c
        r = np.hypot(delta[:, 0], delta[:, 1])
        return r, -delta / r[:, None]

    center, radii = _chebyshev_zone(distance, jacobian, center0, np.full(2, step), np.sqrt(2.0) * step,
                                    len(points2d), max_iterations=max_iterations)
    mean = (radii.max() + radii.min()) / 2.0
    return ZoneCircle(center=center, radius_inner=float(radii.min()), radius_outer=float(radii.max()),
                      width=float(radii.max() - radii.min()), residuals=radii - mean)


def roundness(points2d, method: str = "least_squares") -> float:
    """Roundness deviation: peak-to-valley of the radial deviations about a reference circle (ISO 12181-1), mm.

    Parameters
    ----------
    points2d : (n, 2) float, mm, a profile in the plane of the section
    method : "least_squares" (RONt about the LSCI, :func:`fit_circle_least_squares`) or
        "minimum_zone" (RONt about the MZCI, :func:`minimum_zone_circle`); minimum zone <= least squares always.

    Returns
    -------
    float, mm
    """
    if method == "least_squares":
        residuals = fit_circle_least_squares(points2d).residuals
        return float(residuals.max() - residuals.min())
    if method == "minimum_zone":
        return minimum_zone_circle(points2d).width
    raise ValueError(f"method must be 'least_squares' or 'minimum_zone', got {method!r}")


# ------------------------------------------------------------------------------------------------------------- cones

@dataclass(frozen=True)
class ConeFit:
    """Least-squares cone (orthogonal distances).

    apex : (3,) float, mm (far away, or inf, for a nearly cylindrical fit)
    axis : (3,) float, unit, from the apex into the cone: the radius grows along +axis
    half_angle_rad : float, > 0, angle between the axis and a generator
    axis_point : (3,) float, mm, the axis' point on the reference plane (see :func:`fit_cone`)
    radius_at_axis_point : float, mm, the cone's radius there (measured perpendicular to the axis)
    residuals : (n,) float, mm, signed orthogonal distance of each point to the cone surface, positive outward
    rms : float, mm, root mean square of the residuals
    half_angle_std_rad : float, standard error of the half angle (from the Jacobian and the residual variance)
    axis_std_rad : float, standard error of the axis direction (root sum of the two tilt variances)
    axis_point_std_mm : float, standard error of the axis position in the reference plane (root sum of two variances)
    error_amplification : float, how far the points determine the cone (:func:`cone_error_amplification`): the
        largest move of the cone's six parameters, as displacements at the cloud's size, per unit RMS change of the
        points' distances; inf when the points do not determine it at all (one ring: every cone through that circle
        fits it)
    """

    apex: np.ndarray
    axis: np.ndarray
    half_angle_rad: float
    axis_point: np.ndarray
    radius_at_axis_point: float
    residuals: np.ndarray
    rms: float
    half_angle_std_rad: float
    axis_std_rad: float
    axis_point_std_mm: float
    error_amplification: float = 1.0


def cone_error_amplification(normal, points_count: int, size_mm: float) -> float:
    """How far a set of points determines a cone: 1 / (the least singular value of the fit's Jacobian J / sqrt(n)),
    with the angular parameters (axis tilts, half angle) as the displacements they make at the cloud's size.

    normal : (6, 6) J^T J of the cone model in (tilt u, tilt v, axis point s, t (mm), radius (mm), half angle) at the
    fit (``_cone_model``). points_count : n. size_mm : the cloud's size (RMS distance of its points from their
    centroid).

    A pattern of errors of RMS e along the points' normals (noise, form) can move the fitted cone by up to
    amplification * e, its axis and half angle counted as the displacement they make over ``size_mm``: a cone probed
    over its whole height and turn gives about 10, over a 2 mm band of its 20 mm height about 70, over a 60 deg arc
    about 90; points on one ring (every cone through that circle fits them: the Jacobian is rank-deficient) give
    10^4 and more (inf when exactly singular). Scale-free: the same for a part and its copy ten times the size.
    """
    scale = np.array([size_mm, size_mm, 1.0, 1.0, 1.0, size_mm])
    scaled = np.asarray(normal, dtype=np.float64) / np.outer(scale, scale) / max(points_count, 1)
    if not np.isfinite(scaled).all():
        return math.inf
    least = float(np.linalg.eigvalsh(scaled)[0])
    # eigenvalues below the rounding of the largest are zero: the points leave a direction of the cone undetermined
    if least <= 1e-14 * float(np.abs(np.diag(scaled)).max() or 1.0):
        return math.inf
    return 1.0 / math.sqrt(least)


def _cone_distance(points, base, axis, radius, half_angle):
    """Signed orthogonal distance of points (n, 3) to a cone given by a point `base` on its axis, its unit `axis`,
    its radius at `base` and its half angle: in the half plane through the axis and a point, with h along the axis and
    r from it, the generator is r = radius + h tan(half_angle), so the distance is (r - radius) cos - h sin.
    Exact for points whose nearest surface point is not beyond the apex. Returns distances and (w, h, r, q_hat)."""
    w = points - base
    h = w @ axis
    radial = w - h[:, None] * axis
    r = np.sqrt(np.einsum("ij,ij->i", radial, radial))
    distance = (r - radius) * np.cos(half_angle) - h * np.sin(half_angle)
    return distance, w, h, r, radial / np.maximum(r, 1e-300)[:, None]


def _cone_model(points, axis0, base0):
    """The cone's residuals and Jacobian in the parameters (u, v, s, t, rho, alpha) about a start axis: axis =
    normalise(axis0 + u e1 + v e2) has no singularity near axis0; the axis point base0 + s e1 + t e2 stays in the plane
    through base0 normal to axis0; rho is the radius there. Neither the apex nor 1/tan(alpha) appears, so a nearly
    cylindrical cone is as well posed as a steep one. Returns (unpack, residuals, jacobian, normal_equations): the
    fits use the compiled normal equations; the numpy residuals and Jacobian are their reference formulation
    (``tests/test_form.py`` compares the two and the Jacobian with finite differences)."""
    e1, e2 = _perpendicular_basis(axis0)

    def unpack(params):
        n = axis0 + params[0] * e1 + params[1] * e2
        return n / np.linalg.norm(n), base0 + params[2] * e1 + params[3] * e2, params[4], params[5], np.linalg.norm(n)

    def residuals(params):
        axis, base, radius, alpha, _ = unpack(params)
        return _cone_distance(points, base, axis, radius, alpha)[0]

    def jacobian(params):
        axis, base, radius, alpha, norm = unpack(params)
        w = points - base
        h = w @ axis
        radial = w - h[:, None] * axis
        r = np.sqrt(np.einsum("ij,ij->i", radial, radial))
        cos, sin = np.cos(alpha), np.sin(alpha)
        project = (np.eye(3) - np.outer(axis, axis)) / norm
        # the unit radial vector q_hat = radial / r, projected on the four directions the parameters move
        directions = np.column_stack([project @ e1, project @ e2, e1, e2])
        q_dir = (radial @ directions) / np.maximum(r, 1e-300)[:, None]
        w_dir = w @ directions[:, :2]
        jac = np.empty((len(points), 6))
        # d(distance)/d(axis) = -cos h q_hat - sin w  (dh/daxis = w, dr/daxis = -h q_hat), through the normalisation
        jac[:, 0] = -cos * h * q_dir[:, 0] - sin * w_dir[:, 0]
        jac[:, 1] = -cos * h * q_dir[:, 1] - sin * w_dir[:, 1]
        # d(distance)/d(base) = -cos q_hat + sin axis  (dh/dbase = -axis, dr/dbase = -q_hat)
        jac[:, 2] = -cos * q_dir[:, 2] + sin * (axis @ e1)
        jac[:, 3] = -cos * q_dir[:, 3] + sin * (axis @ e2)
        jac[:, 4] = -cos
        jac[:, 5] = -(r - radius) * sin - h * cos
        return jac

    contiguous = np.ascontiguousarray(points, dtype=np.float64)

    def normal_equations(params):
        """(J^T J (6, 6), J^T f (6,), f (n,), sum f^2) at params, in one compiled pass (the same formulas as
        :func:`jacobian`, per point; see :mod:`trueaxis.inspect.kernels`)."""
        axis, base, radius, alpha, norm = unpack(params)
        project = (np.eye(3) - np.outer(axis, axis)) / norm
        f, normal, gradient = np.empty(len(contiguous)), np.empty((6, 6)), np.empty(6)
        cost = cone_normal_equations(contiguous, base, axis, e1, e2, np.ascontiguousarray(project @ e1),
                                     np.ascontiguousarray(project @ e2), float(radius), float(alpha), f, normal,
                                     gradient)
        return normal, gradient, f, cost

    return unpack, residuals, jacobian, normal_equations


def _algebraic_cone_start(points, axis0, base0):
    """Start parameters for a start axis: in the frame (e1, e2, axis0) about base0 the cone is
    x^2 + y^2 = 2 cx x + 2 cy y + (rho^2 - cx^2 - cy^2) + 2 rho k z + k^2 z^2  (k = tan half angle), linear in
    (2cx, 2cy, rho^2 - |c|^2, 2 rho k, k^2): a Kasa-like fit that also works on a partial cone."""
    e1, e2 = _perpendicular_basis(axis0)
    local = points - base0
    x, y, z = local @ e1, local @ e2, local @ axis0
    design = np.column_stack([x, y, np.ones_like(x), z, z * z])
    coef = np.linalg.lstsq(design, x * x + y * y, rcond=None)[0]
    cx, cy = coef[0] / 2.0, coef[1] / 2.0
    rho = np.sqrt(max(coef[2] + cx * cx + cy * cy, 1e-12))
    return np.array([0.0, 0.0, cx, cy, rho, np.arctan(coef[3] / (2.0 * rho))])


def _fit_cone_from(points, axis0, base0, start=None):
    """One Levenberg-Marquardt fit from a start axis (and, optionally, start parameters); returns (parameters,
    unpack function)."""
    if start is None:
        start = _algebraic_cone_start(points, axis0, base0)
    unpack, _, _, normal_equations = _cone_model(points, axis0, base0)
    return _levenberg_marquardt(start, normal_equations)[0], unpack


def _quadric_cone_axis(points) -> np.ndarray:
    """Axis direction of a cone from a general quadric fitted algebraically (no start needed, no restarts).

    A circular cone is the quadric (p - a)^T A (p - a) = 0 with A = I - (1 + k^2) u u^T (u its axis, k = tan half
    angle): A has a double eigenvalue (the radial directions) and a single one whose eigenvector is the axis. The
    quadric q(p) = p^T A p + b . p + c with |coefficients| = 1 minimising sum q(p_i)^2 is the right singular vector of
    the design matrix with the least singular value (Pratt-like algebraic fit); the axis is the eigenvector of A whose
    eigenvalue stands apart from the other two.
    """
    centre = points.mean(axis=0)
    local = points - centre
    local = local / np.sqrt((local ** 2).sum(axis=1).mean())
    x, y, z = local.T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z, np.ones_like(x)])
    q = np.linalg.svd(design, full_matrices=False)[2][-1]
    quadric = np.array([[q[0], q[3], q[4]], [q[3], q[1], q[5]], [q[4], q[5], q[2]]])
    values, vectors = np.linalg.eigh(quadric)
    # the double eigenvalue is the closer pair: the axis belongs to the remaining one
    return vectors[:, 0] if values[2] - values[1] < values[1] - values[0] else vectors[:, 2]


def _gauss_newton_polish(params, normal_equations, max_iterations: int = 20):
    """Gauss-Newton from a start near the least-squares minimum; each step solves the 6 x 6 normal equations
    J^T J d = -J^T f (scaled by the diagonal). The decrease a step promises, Delta = d^T J^T J d, measures it in
    standard errors: k^2 = Delta (n - 6) / sum f^2. Near a minimum with non-zero residuals Gauss-Newton converges
    linearly, each step smaller than the one before by a rate r (measured from the two); when r k < 1e-4 (what is
    left after this step, in standard errors) the step is the last one, its normal equations kept from before it
    (they change by that step: negligibly for the standard errors). Stops too when a step promises less than the
    rounding of the sum of squares, or fails to lower it. ``normal_equations(params)`` gives (J^T J, J^T f, f,
    sum f^2) in one pass over the points. Returns (params, J^T J, residuals at params)."""
    normal, gradient, f, cost = normal_equations(params)
    n = max(len(f) - len(params), 1)
    previous = None
    for _ in range(max_iterations):
        scale = np.sqrt(np.diag(normal))
        scale[scale == 0] = 1.0
        step = -np.linalg.solve(normal / np.outer(scale, scale), gradient / scale) / scale
        promised = -float(gradient @ step)
        if promised <= 1e-13 * cost:
            break
        trial = params + step
        # the step in standard errors, and what is left after it: Gauss-Newton converges linearly near a
        # non-zero-residual minimum, at a rate measured by the ratio of successive steps
        size = np.sqrt(promised * n / cost)
        rate = 1.0 if previous is None else min(1.0, np.sqrt(promised / previous))
        previous = promised
        last = size * rate <= 1e-4
        normal_new, gradient_new, f_new, cost_new = normal_equations(trial)
        if not cost_new < cost:
            break  # at the minimum to rounding: the step is noise
        if last:
            params, f = trial, f_new
            break
        params, normal, gradient, f, cost = trial, normal_new, gradient_new, f_new, cost_new
    return params, normal, f


CONE_SAMPLE = 20_000  # points of the coarse fit; the polish uses all of them


def fit_cone(points, initial_axis=None, initial_apex=None, reference_plane=None) -> ConeFit:
    """Least-squares cone: minimise the sum of squared orthogonal distances of the points to the cone surface.

    Method: geometric (orthogonal-distance) least squares as in Forbes, "Least-squares best-fit geometric elements",
    NPL DITC 140/89 (1989), and Shakarji, "Least-squares fitting algorithms of the NIST algorithm testing system",
    J. Res. NIST 103 (1998), with the exact Jacobian. The axis is parameterised as normalise(a0 + u e1 + v e2) about
    the start axis a0 and the axis point moves in the plane normal to a0, so the parameterisation has no singularity
    near the start; the cone's size is its radius on that plane, not its apex, so a small half angle (far apex) is
    well posed.

    One start, no restarts: the start axis is ``initial_axis`` (the part's nominal axis), else the axis of a general
    quadric fitted algebraically (:func:`_quadric_cone_axis`); an algebraic cone fit for that axis gives the other
    parameters. Levenberg-Marquardt converges on an evenly strided sample of at most ``CONE_SAMPLE`` points; then
    Gauss-Newton on all points, in the parameterisation centred on that solution (where the Jacobian is well
    conditioned and the standard errors mean what they say), converges quadratically to the least-squares cone of
    all points in a few passes over them.

    Parameters
    ----------
    points : (n, 3) float, mm, n >= 6, on the cone's surface
    initial_axis : (3,) float, optional start direction of the axis (either sign)
    initial_apex : (3,) float, mm, optional point on the start axis (default: the points' centroid)
    reference_plane : optional (point (3,), normal (3,)) pair: ``axis_point`` is where the fitted axis crosses this
        plane (e.g. the part's base plane, or any stated reference plane), and ``radius_at_axis_point`` is the cone's
        radius in the plane normal to the axis there. Default: the foot of the points' centroid on the fitted axis.

    Returns
    -------
    ConeFit, with the axis pointing from the apex into the cone and a positive half angle.

    Standard errors are sigma * sqrt(diag((J^T J)^-1)) with sigma^2 = sum(residuals^2) / (n - 6), the usual linearised
    estimate: meaningful for independent noise, not for systematic form error. They say nothing when the points do not
    determine the cone (points on one ring fit a family of cones exactly: residuals and standard errors near zero);
    ``error_amplification`` says that (:func:`cone_error_amplification`).
    """
    points = _points(points, (3,), 6)
    centroid = points.mean(axis=0)
    stride = max(1, -(-len(points) // CONE_SAMPLE))
    sample = points[::stride]
    if initial_axis is None:
        if initial_apex is not None:
            raise ValueError("initial_apex needs initial_axis")
        axis0 = _quadric_cone_axis(sample)
    else:
        axis0 = _unit(initial_axis, "initial_axis")
    base0 = centroid
    if initial_apex is not None:
        apex = np.asarray(initial_apex, dtype=np.float64).reshape(3)
        base0 = apex + ((centroid - apex) @ axis0) * axis0  # the centroid's foot on the start axis
    solution, unpack = _fit_cone_from(sample, axis0, base0)
    axis, base, radius, alpha, _ = unpack(solution)
    # re-centre on the coarse solution: the axis point to the centroid's foot, the radius along the generator
    shift = (centroid - base) @ axis
    base, radius = base + shift * axis, radius + shift * np.tan(alpha)
    unpack, _, _, normal_equations = _cone_model(points, axis, base)
    params, normal, residuals = _gauss_newton_polish(np.array([0.0, 0.0, 0.0, 0.0, radius, alpha]),
                                                     normal_equations)
    axis, base, radius, alpha, norm = unpack(params)
    if alpha < 0:  # radius grows along -axis: turn the axis round so that the half angle is positive
        axis, alpha = -axis, -alpha
    apex = base - (radius / np.tan(alpha)) * axis if alpha != 0 else np.full(3, np.inf)

    if reference_plane is None:
        axis_point = base + ((centroid - base) @ axis) * axis
    else:
        plane_point = np.asarray(reference_plane[0], dtype=np.float64).reshape(3)
        plane_normal = _unit(reference_plane[1], "reference_plane normal")
        along = axis @ plane_normal
        if abs(along) < 1e-12:
            raise ValueError("the fitted cone axis is parallel to the reference plane")
        axis_point = base + (((plane_point - base) @ plane_normal) / along) * axis
    radius_at_point = radius + ((axis_point - base) @ axis) * np.tan(alpha)

    n = len(points)
    dof = max(n - 6, 1)
    sigma2 = float(residuals @ residuals) / dof
    try:
        covariance = sigma2 * np.linalg.inv(normal)
        std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    except np.linalg.LinAlgError:
        std = np.full(6, np.nan)
    size = float(np.sqrt(((points - centroid) ** 2).sum(axis=1).mean()))
    return ConeFit(apex=apex, axis=axis, half_angle_rad=float(alpha), axis_point=axis_point,
                   radius_at_axis_point=float(radius_at_point), residuals=residuals,
                   rms=float(np.sqrt(np.mean(residuals ** 2))), half_angle_std_rad=float(std[5]),
                   axis_std_rad=float(np.hypot(std[0], std[1]) / norm),
                   axis_point_std_mm=float(np.hypot(std[2], std[3])),
                   error_amplification=cone_error_amplification(normal, n, size))


def section_ring(points, axis_point, axis_dir, height: float, tolerance: float, half_angle_rad: float | None = None,
                 return_index: bool = False):
    """Points of a surface of revolution near a height along its axis, in 2D coordinates of the section plane.

    Parameters
    ----------
    points : (n, 3) float, mm
    axis_point : (3,) float, mm, origin of the heights and of the 2D coordinates
    axis_dir : (3,) float, the axis' direction (normalised here)
    height : float, mm, the section's height along axis_dir from axis_point
    tolerance : float > 0, mm, half thickness of the slab of points taken
    half_angle_rad : optional float: for a cone (radius growing along +axis_dir), move each point along the generator
        to the section plane, removing the radial spread of the slab, (h - height) tan(half_angle) (up to
        tolerance * tan(half_angle)), which would otherwise add to the roundness.
    return_index : also return the indices of the points taken

    Returns
    -------
    points2d : (m, 2) float, mm, coordinates along (e1, e2), a right-handed basis of the section plane with
        (e1, e2, axis_dir) right-handed; e1 is the unit vector of world X, Y or Z least parallel to the axis, crossed.
    index : (m,) int, only with return_index
    """
    points = _points(points, (3,), 0)
    axis = _unit(axis_dir, "axis_dir")
    origin = np.asarray(axis_point, dtype=np.float64).reshape(3)
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be > 0, got {tolerance}")
    local = points - origin
    h = local @ axis
    index = np.flatnonzero(np.abs(h - height) <= tolerance)
    e1, e2 = _perpendicular_basis(axis)
    planar = np.column_stack([local[index] @ e1, local[index] @ e2])
    if half_angle_rad is not None and len(index):
        radii = np.hypot(*planar.T)
        shift = (h[index] - height) * np.tan(half_angle_rad)
        planar *= ((radii - shift) / np.maximum(radii, 1e-300))[:, None]
    return (planar, index) if return_index else planar


# --------------------------------------------------------------------------------------------------- planes and lines

@dataclass(frozen=True)
class PlaneFit:
    """Least-squares plane (orthogonal distances).

    point : (3,) float, mm, the centroid of the points (on the plane)
    normal : (3,) float, unit, largest-magnitude component positive
    residuals : (n,) float, mm, signed distance (p - point) . normal
    """

    point: np.ndarray
    normal: np.ndarray
    residuals: np.ndarray


@dataclass(frozen=True)
class LineFit:
    """Least-squares line (orthogonal distances).

    point : (d,) float, mm, the centroid of the points (on the line), d = 2 or 3
    direction : (d,) float, unit, largest-magnitude component positive
    residuals : (n,) float, mm: in 2D the signed distance along the left normal (-dy, dx); in 3D the distance (>= 0)
    """

    point: np.ndarray
    direction: np.ndarray
    residuals: np.ndarray


def fit_plane(points) -> PlaneFit:
    """Least-squares plane: minimise the sum of squared orthogonal distances (total least squares).

    Method: the plane passes through the centroid; its normal is the right singular vector of the centred points with
    the least singular value (Forbes, NPL DITC 140/89, §3; Shakarji, J. Res. NIST 103 (1998)).

    Parameters
    ----------
    points : (n, 3) float, mm, n >= 3, not all on one line

    Returns
    -------
    PlaneFit
    """
    points = _points(points, (3,), 3)
    centroid = points.mean(axis=0)
    _, singular, vt = np.linalg.svd(points - centroid, full_matrices=False)
    if singular[1] <= 1e-12 * max(singular[0], 1e-300):
        raise ValueError("points lie on a line (or a point): no unique plane")
    normal = _orient(vt[2])
    return PlaneFit(point=centroid, normal=normal, residuals=(points - centroid) @ normal)


def fit_line(points) -> LineFit:
    """Least-squares line in 2D or 3D: minimise the sum of squared orthogonal distances (total least squares).

    Method: the line passes through the centroid along the right singular vector of the centred points with the
    largest singular value (Forbes, NPL DITC 140/89, §3).

    Parameters
    ----------
    points : (n, 2) or (n, 3) float, mm, n >= 2, not all the same point

    Returns
    -------
    LineFit
    """
    points = _points(points, (2, 3), 2)
    centroid = points.mean(axis=0)
    _, singular, vt = np.linalg.svd(points - centroid, full_matrices=False)
    if singular[0] == 0.0:
        raise ValueError("points are all the same point: no line")
    direction = _orient(vt[0])
    return LineFit(point=centroid, direction=direction, residuals=_line_deviation(points, centroid, direction))


def _line_deviation(points, point, direction):
    local = points - point
    if points.shape[1] == 2:
        return local @ np.array([-direction[1], direction[0]])
    return np.linalg.norm(local - np.outer(local @ direction, direction), axis=1)


def straightness(points, line=None, method: str = "least_squares") -> float:
    """Straightness deviation of a profile, mm (ISO 12780-1).

    Parameters
    ----------
    points : (n, 2) float, mm, a profile in its plane (a line in a plane); or (n, 3) with method "least_squares"
    line : optional reference (LineFit, or a (point, direction) pair) for "least_squares"; default: fit_line(points)
    method :
        "least_squares": peak-to-valley of the deviations from the least-squares reference line (LSLI, STRt). In 2D
        the signed deviations; in 3D the diameter of the cylinder about the line that holds all points
        (2 max distance).
        "minimum_zone": width of the narrowest pair of parallel lines enclosing the 2D profile (MZLI). Exact: the
        minimum width of a point set is attained with one side flush with an edge of its convex hull (Houle &
        Toussaint, IEEE PAMI 10 (1988), "Computing the width of a set"), so every hull edge is tried.
        Always <= the least-squares value.

    Returns
    -------
    float, mm
    """
    if method == "least_squares":
        points = _points(points, (2, 3), 2)
        if line is None:
            line = fit_line(points)
        point, direction = (line.point, line.direction) if isinstance(line, LineFit) else line
        point = np.asarray(point, dtype=np.float64).reshape(points.shape[1])
        direction = _unit(direction, "line direction")
        if direction.shape != (points.shape[1],):
            raise ValueError("line and points must have the same dimension")
        deviation = _line_deviation(points, point, direction)
        return float(deviation.max() - deviation.min()) if points.shape[1] == 2 else float(2.0 * deviation.max())
    if method == "minimum_zone":
        if line is not None:
            raise ValueError("the minimum-zone line is found, not given: pass line=None")
        points = _points(points, (2,), 2)
        return _minimum_width(points)
    raise ValueError(f"method must be 'least_squares' or 'minimum_zone', got {method!r}")


def _minimum_width(points2d: np.ndarray) -> float:
    """Minimum width of a planar point set over all directions (edges of the convex hull, Houle & Toussaint 1988)."""
    centred = points2d - points2d.mean(axis=0)
    scale = np.abs(centred).max()
    if scale == 0.0:
        return 0.0
    from scipy.spatial import ConvexHull  # here: scipy.spatial's import is 0.3 s that most inspections do not need

    try:
        hull = ConvexHull(centred / scale)
    except Exception:  # Qhull refuses a degenerate (collinear) set: its width is 0 to machine precision
        return float(straightness(points2d, method="least_squares"))
    vertices = centred[hull.vertices]
    # edges between consecutive hull vertices (counter-clockwise); the width for an edge is the farthest vertex from it
    edges = np.roll(vertices, -1, axis=0) - vertices
    normals = np.column_stack([-edges[:, 1], edges[:, 0]]) / np.linalg.norm(edges, axis=1)[:, None]
    # |(v_j - v_i) . n_i| for every edge i and vertex j, vectorised as a (h, h) table
    offsets = vertices @ normals.T - np.einsum("ij,ij->i", vertices, normals)[None, :]
    return float(np.abs(offsets).max(axis=0).min())


def parallelism(plane_a_points, plane_b) -> float:
    """Parallelism of a plane surface to a datum plane, mm (ISO 1101): the distance between the two planes parallel
    to the datum that enclose the toleranced surface's points, i.e. the peak-to-valley of their distances to the datum.

    Parameters
    ----------
    plane_a_points : (n, 3) float, mm, the toleranced surface's points
    plane_b : the datum: a PlaneFit (e.g. fit_plane of the datum surface's points), or a (point (3,), normal (3,)) pair

    Returns
    -------
    float, mm
    """
    points = _points(plane_a_points, (3,), 1, "plane_a_points")
    point, normal = (plane_b.point, plane_b.normal) if isinstance(plane_b, PlaneFit) else plane_b
    point = np.asarray(point, dtype=np.float64).reshape(3)
    normal = _unit(normal, "plane_b normal")
    distance = (points - point) @ normal
    return float(distance.max() - distance.min())


# ------------------------------------------------------------------------------------------ Chebyshev (minimum zone)

def _zone_linear_program(slopes, values, bound: float, max_pivots: int = 10_000):
    """The linear program of one minimum-zone step: minimise a - b over (x, a, b) subject to
    b <= values_i + slopes_i . x <= a for every point i and |x_j| <= bound.

    Method: the primal simplex method on its dual, which has only k + 2 rows (k the parameters): minimise h . lam
    subject to G^T lam = -c, lam >= 0, G and h the constraints' rows and right-hand sides, c = (0, 1, -1). A basis
    is k + 2 of the 2 m + 2 k dual columns; a feasible one is known at once (the point of largest and the point of
    smallest value, and one side of each box bound), so no first phase is needed. Each pivot prices every column
    (vectorised) and solves two (k + 2)-square systems; at the optimum the basis' multipliers are the primal (x, a, b)
    (G pi <= h is the dual's optimality). The largest-decrease rule picks the entering column, Bland's rule after a
    run of degenerate pivots (no cycling).

    Why not scipy's ``linprog``: importing scipy.optimize costs ``inspect`` 0.45 s, where these programs (4 to 7
    variables, a few thousand constraints) take milliseconds; ``tests/test_form.py`` checks this against HiGHS.

    slopes : (m, k) float, values : (m,) float, bound : float > 0. Returns (x (k,), a - b).
    """
    m, k = slopes.shape
    n_rows = k + 2
    # dual columns: 0..m-1 the upper rows (slopes_i, -1, 0), m..2m-1 the lower rows (-slopes_i, 0, 1),
    # then +e_j and -e_j (the box); their costs h
    cost = np.r_[-values, values, np.full(2 * k, bound)]
    rhs = np.r_[np.zeros(k), -1.0, 1.0]

    def column(index):
        col = np.zeros(n_rows)
        if index < m:
            col[:k], col[k] = slopes[index], -1.0
        elif index < 2 * m:
            col[:k], col[k + 1] = -slopes[index - m], 1.0
        else:
            j = index - 2 * m
            col[j % k] = 1.0 if j < k else -1.0
        return col

    top, low = int(np.argmax(values)), int(np.argmin(values))
    difference = slopes[top] - slopes[low]
    basis = [top, m + low] + [2 * m + k + j if difference[j] > 0 else 2 * m + j for j in range(k)]
    tolerance = 1e-12 * max(1.0, float(np.abs(cost).max()))
    degenerate = 0
    for _ in range(max_pivots):
        matrix = np.column_stack([column(i) for i in basis])
        weights = np.linalg.solve(matrix, rhs)  # the basic dual variables, >= 0 (to rounding)
        pi = np.linalg.solve(matrix.T, cost[basis])  # the multipliers: the primal (x, a, b)
        along = slopes @ pi[:k]
        reduced = np.r_[-values - along + pi[k], values + along - pi[k + 1], bound - pi[:k], bound + pi[:k]]
        reduced[basis] = 0.0
        if degenerate > 50:
            candidates = np.flatnonzero(reduced < -tolerance)
            entering = int(candidates[0]) if len(candidates) else -1
        else:
            entering = int(np.argmin(reduced)) if reduced.min() < -tolerance else -1
        if entering < 0:
            return pi[:k], float(pi[k] - pi[k + 1])
        direction = np.linalg.solve(matrix, column(entering))
        positive = direction > 1e-12
        if not positive.any():  # the dual unbounded: the primal infeasible, which it never is (x = 0 is feasible)
            raise RuntimeError("minimum-zone linear program: no bounded step (rounding)")
        ratios = np.where(positive, np.maximum(weights, 0.0) / np.where(positive, direction, 1.0), np.inf)
        leaving = int(np.argmin(ratios)) if degenerate <= 50 else int(
            min(np.flatnonzero(ratios == ratios.min()), key=lambda r: basis[r]))
        degenerate = degenerate + 1 if ratios[leaving] <= 1e-15 else 0
        basis[leaving] = entering
    raise RuntimeError(f"minimum-zone linear program: no optimum after {max_pivots} pivots")


def _chebyshev_zone(distance, jacobian, theta0, step_scale, lipschitz: float, n_points: int,
                    candidates: int = 1500, max_iterations: int = 300):
    """Minimise the zone width max_i f_i(theta) - min_i f_i(theta) over the parameters theta (the feature's
    location and orientation; its size is the zone's middle, free).

    Method: sequential linear programming with a trust region (Dhanish & Shunmugam, Precision Engineering 13 (1991)),
    as in :func:`minimum_zone_circle`: about theta the distances are f_i + J_i S x, the linear program

        minimise  a - b   over (x, a, b)   subject to   b <= f_i + J_i S x <= a,   |x|_inf <= t

    gives a step S x; it is accepted when the exact width over *all* points decreases. Only the extreme points can
    touch the zone: each linear program holds the ``candidates`` points of largest and of smallest f (found in O(n)
    with ``argpartition``), and the step bound t is capped so that no other point can reach the zone's edges in the
    linear model (|J_i S x| <= lipschitz * t < the margin to the nearest left-out point): the linear program on the
    candidates is then the linear program on all points, and the fixed point is first-order optimal for the whole
    set. The linearisation error is second order in the step, so near the solution the steps converge like Newton's.

    distance(theta) -> (n,) f of all points; jacobian(theta, index) -> (f[index], J[index] (m, k)).
    step_scale : (k,) S, the size of a unit step of each parameter. lipschitz : an upper bound of the 1-norm of the
    rows of J S over all points. Returns (theta, f at theta).
    """
    theta = np.asarray(theta0, dtype=np.float64).copy()
    f = distance(theta)
    width = float(np.ptp(f))
    size = max(float(np.abs(f).max()), 1e-300)
    k = len(theta)
    trust = 1.0
    for _ in range(max_iterations):
        if width <= 1e-14 * size:
            break  # a perfect form to machine precision
        if n_points > 2 * candidates + 2:
            top = np.argpartition(f, n_points - candidates - 1)
            outer, rest_hi = top[n_points - candidates:], f[top[n_points - candidates - 1]]
            bottom = np.argpartition(f, candidates)
            inner, rest_lo = bottom[:candidates], f[bottom[candidates]]
            index = np.union1d(outer, inner)
            # the nearest left-out point is this far inside the zone: keep the linear model's motion below half of it
            margin = min(f.max() - rest_hi, rest_lo - f.min())
            cap = 0.5 * margin / max(lipschitz, 1e-300)
        else:
            index, cap = np.arange(n_points), np.inf
        bound = min(trust, cap)
        fi, ji = jacobian(theta, index)
        js = ji * step_scale
        scale = max(width, 1e-12 * size)
        dev = (fi - fi.mean()) / scale
        m = len(index)
        x, zone = _zone_linear_program(js / scale, dev, bound)
        predicted = width - zone * scale
        if predicted <= 1e-12 * max(width, 1e-300) or np.abs(x).max() == 0.0:
            if bound < trust and np.abs(x).max() > 0.99 * bound:
                pass  # the cap, not the optimum, stopped the step: take it and look again
            else:
                break  # the linear model sees no further decrease: first-order optimal
        new_theta = theta + step_scale * x
        new_f = distance(new_theta)
        new_width = float(np.ptp(new_f))
        ratio = (width - new_width) / predicted if predicted > 0 else -1.0
        if ratio > 0:
            theta, f, width = new_theta, new_f, new_width
        if ratio > 0.75 and np.abs(x).max() > 0.99 * bound:
            trust = 2.0 * min(trust, bound)
        elif ratio < 0.25:
            trust = 0.25 * min(trust, bound)
        if trust < 1e-13:
            break
    return theta, f


# ----------------------------------------------------------------------------------------------------------- spheres

@dataclass(frozen=True)
class SphereFit:
    """Least-squares sphere (Gauss).

    center : (3,) float, mm. radius : float, mm.
    residuals : (n,) float, mm, |p - center| - radius, positive outward. rms : float, mm.
    """

    center: np.ndarray
    radius: float
    residuals: np.ndarray
    rms: float


@dataclass(frozen=True)
class ZoneSphere:
    """Minimum-zone spheres (Chebyshev): two concentric spheres enclosing the points, of least radial separation.

    center : (3,) float, mm. radius_inner, radius_outer : float, mm. width : float, mm, the form deviation.
    residuals : (n,) float, mm, |p - center| - (radius_inner + radius_outer) / 2.
    """

    center: np.ndarray
    radius_inner: float
    radius_outer: float
    width: float
    residuals: np.ndarray


def fit_sphere(points) -> SphereFit:
    """Least-squares sphere: minimise the sum of squared radial distances |p - c| - R.

    Method: the algebraic fit |p|^2 = 2 c . p + (R^2 - |c|^2) (linear least squares) for the start, then
    Levenberg-Marquardt on the geometric residuals with their exact Jacobian (Forbes, NPL DITC 140/89, §4;
    Shakarji, J. Res. NIST 103 (1998)).

    points : (n, 3) float, mm, n >= 4, not all on one plane (or circle). Returns SphereFit.
    """
    points = _points(points, (3,), 4)
    origin = points.mean(axis=0)
    local = points - origin
    scale = np.sqrt((local ** 2).sum(axis=1).mean())
    if scale == 0.0:
        raise ValueError("points are all the same point")
    local = local / scale
    design = np.column_stack([2.0 * local, np.ones(len(local))])
    solution, _, rank, singular = np.linalg.lstsq(design, (local ** 2).sum(axis=1), rcond=None)
    if rank < 4 or singular[-1] < 1e-9 * singular[0]:
        raise ValueError("points lie on a plane or a circle: no unique sphere through them")
    start = np.r_[solution[:3], np.sqrt(solution[3] + solution[:3] @ solution[:3])]

    def residuals(params):
        return np.linalg.norm(local - params[:3], axis=1) - params[3]

    def jacobian(params):
        delta = local - params[:3]
        return np.column_stack([-delta / np.linalg.norm(delta, axis=1)[:, None], -np.ones(len(delta))])

    solution = _levenberg_marquardt(start, _normal_equations_of(residuals, jacobian))[0]
    center = origin + solution[:3] * scale
    radius = float(solution[3] * scale)
    res = np.linalg.norm(points - center, axis=1) - radius
    return SphereFit(center=center, radius=radius, residuals=res, rms=float(np.sqrt(np.mean(res ** 2))))


def minimum_zone_sphere(points, start=None) -> ZoneSphere:
    """Minimum-zone spheres (Chebyshev): the centre c minimising max_i |p_i - c| - min_i |p_i - c|.

    Method: :func:`_chebyshev_zone` (sequential linear programming on the extreme points) from the least-squares
    centre (or ``start``); a local minimum near it, which is the minimum zone for a sphere-like profile.

    points : (n, 3) float, mm, n >= 5. start : optional (3,) centre. Returns ZoneSphere.
    """
    points = _points(points, (3,), 5)
    fit = fit_sphere(points) if start is None else None
    center0 = fit.center if fit is not None else np.asarray(start, dtype=np.float64).reshape(3)
    width0 = float(np.ptp(np.linalg.norm(points - center0, axis=1)))
    step = max(width0, 1e-12 * np.abs(points).max())

    def distance(c):
        return np.linalg.norm(points - c, axis=1)

    def jacobian(c, index):
        delta = points[index] - c
        r = np.linalg.norm(delta, axis=1)
        return r, -delta / r[:, None]

    center, radii = _chebyshev_zone(distance, jacobian, center0, np.full(3, step), np.sqrt(3.0) * step, len(points))
    mean = (radii.max() + radii.min()) / 2.0
    return ZoneSphere(center=center, radius_inner=float(radii.min()), radius_outer=float(radii.max()),
                      width=float(np.ptp(radii)), residuals=radii - mean)


# ------------------------------------------------------------------------------------------------- minimum-zone plane

@dataclass(frozen=True)
class ZonePlane:
    """Minimum-zone planes (Chebyshev, ISO 12781 MZPL): two parallel planes enclosing the points, of least distance.

    point : (3,) float, mm, on the mid plane. normal : (3,) unit, largest-magnitude component positive.
    width : float, mm, the flatness deviation. residuals : (n,) float, mm, signed distances to the mid plane.
    """

    point: np.ndarray
    normal: np.ndarray
    width: float
    residuals: np.ndarray


def minimum_zone_plane(points) -> ZonePlane:
    """Minimum-zone planes: the normal n minimising max_i n . p_i - min_i n . p_i (flatness, ISO 12781-1 MZPL).

    Method: :func:`_chebyshev_zone` from the least-squares plane's normal, n = normalise(n0 + u e1 + v e2): only the
    extreme points (which lie on the convex hull) can touch the zone. Always <= the least-squares peak-to-valley.

    points : (n, 3) float, mm, n >= 4, not all on one line. Returns ZonePlane.
    """
    points = _points(points, (3,), 4)
    ls = fit_plane(points)
    n0 = ls.normal
    e1, e2 = _perpendicular_basis(n0)
    local = points - ls.point
    extent = float(np.abs(local).max())
    step = max(float(np.ptp(ls.residuals)), 1e-12 * extent) / max(extent, 1e-300)

    def normal_of(theta):
        n = n0 + theta[0] * e1 + theta[1] * e2
        return n / np.linalg.norm(n), np.linalg.norm(n)

    def distance(theta):
        return local @ normal_of(theta)[0]

    def jacobian(theta, index):
        n, norm = normal_of(theta)
        project = (np.eye(3) - np.outer(n, n)) / norm
        block = local[index]
        return block @ n, np.column_stack([block @ (project @ e1), block @ (project @ e2)])

    # |J_i S x|_1 <= |p_i| (|e1| + |e2|) step: 2 sqrt(3) extent step bounds every row
    theta, f = _chebyshev_zone(distance, jacobian, np.zeros(2), np.full(2, step), 2.0 * np.sqrt(3.0) * extent * step,
                               len(points))
    n = normal_of(theta)[0]
    sign = 1.0 if n[np.argmax(np.abs(n))] >= 0 else -1.0
    mid = (f.max() + f.min()) / 2.0
    return ZonePlane(point=ls.point + mid * n, normal=sign * n, width=float(np.ptp(f)), residuals=sign * (f - mid))


# --------------------------------------------------------------------------------------------------------- cylinders

@dataclass(frozen=True)
class CylinderFit:
    """Least-squares cylinder (Gauss).

    axis : (3,) unit, largest-magnitude component positive. axis_point : (3,) mm, the axis' point nearest the
    points' centroid. radius : float, mm. residuals : (n,) mm, distance to the axis - radius. rms : float, mm.
    """

    axis: np.ndarray
    axis_point: np.ndarray
    radius: float
    residuals: np.ndarray
    rms: float


@dataclass(frozen=True)
class ZoneCylinder:
    """Minimum-zone cylinders (Chebyshev, ISO 12180 MZCY): two coaxial cylinders enclosing the points, of least
    radial separation. axis, axis_point as CylinderFit; radius_inner, radius_outer, width (the cylindricity), mm;
    residuals : (n,) mm, distance to the axis - (radius_inner + radius_outer) / 2."""

    axis: np.ndarray
    axis_point: np.ndarray
    radius_inner: float
    radius_outer: float
    width: float
    residuals: np.ndarray


def _line_frame(axis0, base0):
    e1, e2 = _perpendicular_basis(axis0)

    def unpack(theta):
        n = axis0 + theta[0] * e1 + theta[1] * e2
        return n / np.linalg.norm(n), base0 + theta[2] * e1 + theta[3] * e2, np.linalg.norm(n)

    def radial(points, theta, index=slice(None)):
        """Distances of points[index] to the axis and their Jacobian (m, 4) in (u, v, s, t)."""
        axis, base, norm = unpack(theta)
        w = points[index] - base
        h = w @ axis
        q = w - h[:, None] * axis
        r = np.linalg.norm(q, axis=1)
        q_hat = q / np.maximum(r, 1e-300)[:, None]
        project = (np.eye(3) - np.outer(axis, axis)) / norm
        d_axis = -h[:, None] * q_hat  # dr/daxis, then through the normalisation
        return r, np.column_stack([d_axis @ (project @ e1), d_axis @ (project @ e2), -q_hat @ e1, -q_hat @ e2]), h

    return unpack, radial


def _finish_axis(axis, base, points):
    """Orient the axis and move its point to the foot of the points' centroid."""
    axis = _orient(axis)
    base = base + ((points.mean(axis=0) - base) @ axis) * axis
    return axis, base


def fit_cylinder(points, initial_axis=None) -> CylinderFit:
    """Least-squares cylinder: minimise the sum of squared distances | distance to the axis - R |^2.

    Method: Levenberg-Marquardt on the geometric residuals with the exact Jacobian (Forbes, NPL DITC 140/89, §5),
    the axis parameterised as normalise(a0 + u e1 + v e2) and its point moving in the plane normal to a0 through the
    centroid (no singularity near the start). Start axis: ``initial_axis``, else the principal directions of the
    points (the axis is the most spread one for a long cylinder, the least spread one for a short one), the best fit
    kept.

    points : (n, 3) float, mm, n >= 6. initial_axis : optional (3,) start direction. Returns CylinderFit.
    """
    points = _points(points, (3,), 6)
    centroid = points.mean(axis=0)
    starts = [_unit(initial_axis, "initial_axis")] if initial_axis is not None else \
        list(np.linalg.svd(points - centroid, full_matrices=False)[2])
    best = None
    for axis0 in starts:
        unpack, radial = _line_frame(axis0, centroid)
        r0 = radial(points, np.zeros(4))[0]

        def residuals(params, radial=radial):
            return radial(points, params[:4])[0] - params[4]

        def jacobian(params, radial=radial):
            return np.column_stack([radial(points, params[:4])[1], -np.ones(len(points))])

        solution, _, _, cost = _levenberg_marquardt(np.r_[np.zeros(4), r0.mean()],
                                                    _normal_equations_of(residuals, jacobian))
        if best is None or cost < best[1]:
            best = (solution, cost, unpack)
    solution, _, unpack = best
    axis, base, _ = unpack(solution[:4])
    axis, base = _finish_axis(axis, base, points)
    w = points - base
    res = np.linalg.norm(w - np.outer(w @ axis, axis), axis=1) - solution[4]
    return CylinderFit(axis=axis, axis_point=base, radius=float(solution[4]), residuals=res,
                       rms=float(np.sqrt(np.mean(res ** 2))))


def minimum_zone_cylinder(points, initial_axis=None) -> ZoneCylinder:
    """Minimum-zone cylinders (cylindricity): the axis minimising max_i r_i - min_i r_i, r_i the distance of p_i to it.

    Method: :func:`_chebyshev_zone` from the least-squares cylinder (a local minimum near it).

    points : (n, 3) float, mm, n >= 6. Returns ZoneCylinder.
    """
    points = _points(points, (3,), 6)
    ls = fit_cylinder(points, initial_axis)
    unpack, radial = _line_frame(ls.axis, ls.axis_point)
    h = (points - ls.axis_point) @ ls.axis
    height = max(float(np.abs(h).max()), 1e-300)
    width0 = max(float(np.ptp(ls.residuals)), 1e-12 * ls.radius)
    scale = np.array([width0 / height, width0 / height, width0, width0])
    # |dr/du| <= |h| / |n|, |dr/ds| <= 1: the rows of J S are bounded by 2 width0 + 2 width0
    theta, r = _chebyshev_zone(lambda t: radial(points, t)[0], lambda t, i: radial(points, t, i)[:2], np.zeros(4),
                               scale, 4.0 * width0 * 1.01, len(points))
    axis, base, _ = unpack(theta)
    axis, base = _finish_axis(axis, base, points)
    mean = (r.max() + r.min()) / 2.0
    return ZoneCylinder(axis=axis, axis_point=base, radius_inner=float(r.min()), radius_outer=float(r.max()),
                        width=float(np.ptp(r)), residuals=r - mean)


# ------------------------------------------------------------------------------------------------------- 3D circles

@dataclass(frozen=True)
class Circle3DFit:
    """Least-squares circle in space (Gauss).

    center : (3,) mm. normal : (3,) unit, of the circle's plane, largest-magnitude component positive.
    radius : float, mm. radial_residuals : (n,) mm, in-plane distance from the centre - radius (+ outward).
    normal_residuals : (n,) mm, signed distance from the circle's plane. rms : float, mm, of the 3D distances.
    """

    center: np.ndarray
    normal: np.ndarray
    radius: float
    radial_residuals: np.ndarray
    normal_residuals: np.ndarray
    rms: float


def fit_circle_3d(points) -> Circle3DFit:
    """Least-squares circle in space: minimise the sum of squared 3D distances of the points to the circle,
    d_i^2 = (n . (p_i - c))^2 + (|p_i - c - (n . (p_i - c)) n| - R)^2, over centre, plane normal and radius at once.

    Method: Forbes, NPL DITC 140/89, §6 (circle in space); start from the least-squares plane and the least-squares
    circle of the points projected on it, then Levenberg-Marquardt on both residual components with the normal
    parameterised as normalise(n0 + u e1 + v e2). A plane fit followed by a 2D circle fit is not the same: the
    plane fit weights the points by their out-of-plane scatter only, and its normal can tilt where the joint fit's
    does not.

    points : (n, 3) float, mm, n >= 4, spread round the circle (not on a line). Returns Circle3DFit.
    """
    points = _points(points, (3,), 4)
    plane = fit_plane(points)
    n0 = plane.normal
    e1, e2 = _perpendicular_basis(n0)
    local = points - plane.point
    circle = fit_circle_least_squares(np.column_stack([local @ e1, local @ e2]))
    start = np.r_[0.0, 0.0, circle.center[0], circle.center[1], 0.0, circle.radius]

    def unpack(params):
        n = n0 + params[0] * e1 + params[1] * e2
        norm = np.linalg.norm(n)
        return n / norm, plane.point + params[2] * e1 + params[3] * e2 + params[4] * n0, params[5], norm

    def parts(params):
        n, c, radius, norm = unpack(params)
        w = points - c
        z = w @ n
        q = w - z[:, None] * n
        rho = np.linalg.norm(q, axis=1)
        return n, c, radius, norm, w, z, q / np.maximum(rho, 1e-300)[:, None], rho

    def residuals(params):
        _, _, radius, _, _, z, _, rho = parts(params)
        return np.r_[z, rho - radius]

    def jacobian(params):
        n, _, _, norm, w, z, q_hat, _ = parts(params)
        project = (np.eye(3) - np.outer(n, n)) / norm
        dn = np.column_stack([project @ e1, project @ e2])  # (3, 2): dn/du, dn/dv
        # z = w . n: dz/dn = w, dz/dc = -n;  rho = |w - z n|: drho/dn = -z q_hat, drho/dc = -q_hat
        dc = np.column_stack([e1, e2, n0])  # (3, 3): dc/ds, dc/dt, dc/dw
        jz = np.column_stack([w @ dn, -(n @ dc) * np.ones((len(w), 1)), np.zeros(len(w))])
        jr = np.column_stack([(-z[:, None] * q_hat) @ dn, -q_hat @ dc, -np.ones(len(w))])
        return np.vstack([jz, jr])

    solution = _levenberg_marquardt(start, _normal_equations_of(residuals, jacobian))[0]
    n, c, radius, _, _, z, _, rho = parts(solution)
    sign = 1.0 if n[np.argmax(np.abs(n))] >= 0 else -1.0
    return Circle3DFit(center=c, normal=sign * n, radius=float(radius), radial_residuals=rho - radius,
                       normal_residuals=sign * z, rms=float(np.sqrt(np.mean(z ** 2 + (rho - radius) ** 2))))
