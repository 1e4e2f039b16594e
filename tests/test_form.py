"""Form evaluation against profiles with known answers, and against second, independent formulations.

Tolerance scale: the parts are ~40 mm in size and float64 carries ~16 digits, so a radius, centre or distance computed
in a few dozen operations is exact to ~1e-13 mm; "exact" checks use 1e-10 mm (1e-9 for fits that iterate), a thousand
times that, still a million times below a CMM's 0.1 um resolution.
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.optimize import least_squares, minimize
from scipy.spatial.transform import Rotation

from trueaxis.inspect import form

from trueaxis.inspect.form import (
    ConeFit, fit_circle_least_squares, fit_cone, fit_line, fit_plane, minimum_zone_circle, parallelism, roundness,
    section_ring, straightness,
)

R = 40.0  # mm, radius of the test profiles (the NAS 979 base radius)
CENTRE = np.array([3.0, -2.0])  # mm, an eccentric centre: nothing may assume the profile is about the origin
THETA = np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False)  # 1 degree sampling, as a CMM scan


def profile(radius_of_theta, centre=CENTRE, theta=THETA):
    return centre + radius_of_theta[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])


def zone_width_at(points2d, centre):
    radii = np.hypot(*(points2d - centre).T)
    return radii.max() - radii.min()


def nelder_mead_minimum_zone(points2d, starts):
    """Second formulation of the minimum zone: minimise the exact max - min radius directly (no linearisation, no LP),
    Nelder-Mead from several starts, keeping the best."""
    best = None
    for start in starts:
        result = minimize(lambda c: zone_width_at(points2d, c), start, method="Nelder-Mead",
                          options=dict(xatol=1e-13, fatol=1e-16, maxiter=20000, maxfev=40000))
        if best is None or result.fun < best.fun:
            best = result
    return best


# ------------------------------------------------------------------------------------------------------------ circle

@pytest.mark.parametrize("arc_deg", [360.0, 90.0])
def test_least_squares_circle_recovers_an_eccentric_circle(arc_deg):
    theta = np.radians(np.linspace(10.0, 10.0 + arc_deg, 200))
    fit = fit_circle_least_squares(profile(np.full(theta.size, R), theta=theta))
    np.testing.assert_allclose(fit.center, CENTRE, atol=1e-10)
    assert abs(fit.radius - R) < 1e-10
    assert np.abs(fit.residuals).max() < 1e-10


def test_roundness_of_a_pure_circle_is_zero_with_both_methods():
    points = profile(np.full(THETA.size, R))
    assert roundness(points, "least_squares") < 1e-10
    assert roundness(points, "minimum_zone") < 1e-10
    np.testing.assert_allclose(minimum_zone_circle(points).center, CENTRE, atol=1e-10)


def test_ovality_roundness_is_twice_the_amplitude_with_both_methods():
    # r = R + e cos 2θ about CENTRE: the deviations about the true centre are e cos 2θ, PV 2e. By symmetry the LS
    # centre is the true centre and the LS radius the mean R; the MZ centre too, with 4 alternating contacts
    # (outer at 0 and π, inner at ±π/2), the Chebyshev optimality condition. So both are 2e.
    e = 0.010
    points = profile(R + e * np.cos(2 * THETA))
    fit = fit_circle_least_squares(points)
    np.testing.assert_allclose(fit.center, CENTRE, atol=1e-10)
    assert abs(fit.radius - R) < 1e-10
    assert abs(roundness(points, "least_squares") - 2 * e) < 1e-10
    zone = minimum_zone_circle(points)
    assert abs(zone.width - 2 * e) < 1e-10
    np.testing.assert_allclose(zone.center, CENTRE, atol=1e-9)


def test_three_lobe_roundness_is_the_sampled_peak_to_valley_with_both_methods():
    # a 3-lobe profile (centreless grinding): harmonic 3 is orthogonal to harmonic 1 on a uniform grid, so the LS
    # centre is the true centre; 3 peaks and 3 valleys alternate, so the true centre is also the MZ centre.
    e, phase = 0.005, 0.3
    deviation = e * np.cos(3 * THETA + phase)
    points = profile(R + deviation)
    expected = deviation.max() - deviation.min()  # the sampled PV, a little under 2e on the 1 degree grid
    assert abs(roundness(points, "least_squares") - expected) < 1e-10
    assert abs(roundness(points, "minimum_zone") - expected) < 1e-10


def test_minimum_zone_agrees_with_nelder_mead_on_the_exact_objective():
    # three profiles where the MZ centre differs from the LS centre: noise, lobes plus noise, a 120 degree arc
    rng = np.random.default_rng(7)
    theta_arc = np.radians(np.linspace(0.0, 120.0, 121))
    cases = [
        profile(R + rng.normal(0.0, 0.002, THETA.size)),
        profile(R + 0.004 * np.cos(5 * THETA) + 0.003 * np.sin(2 * THETA) + rng.normal(0.0, 0.001, THETA.size)),
        profile(R + 0.003 * np.cos(7 * theta_arc) + rng.normal(0.0, 0.001, theta_arc.size), theta=theta_arc),
    ]
    for points in cases:
        zone = minimum_zone_circle(points)
        ls_centre = fit_circle_least_squares(points).center
        starts = [ls_centre + offset for offset in ([0, 0], [0.01, 0], [0, -0.01], [-0.005, 0.005])]
        reference = nelder_mead_minimum_zone(points, starts)
        # both minimise the same exact width; the linear programs reach a vertex of the Chebyshev problem, Nelder-Mead
        # creeps to it: agreement to 1e-9 mm (1/1000 of a nanometre-scale) is agreement, and the LP may only win
        assert abs(zone.width - reference.fun) < 1e-9, (zone.width, reference.fun)
        assert zone.width <= reference.fun + 1e-12
        assert abs(zone.width - zone_width_at(points, zone.center)) < 1e-12
        assert zone.width <= roundness(points, "least_squares") + 1e-12


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise_um=st.floats(0.1, 50.0), n=st.integers(8, 400),
       arc_deg=st.floats(90.0, 360.0))
def test_minimum_zone_never_exceeds_least_squares_and_is_locally_minimal(seed, noise_um, n, arc_deg):
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0.0, arc_deg, n))
    points = profile(R + rng.normal(0.0, noise_um * 1e-3, n), theta=theta)
    zone = minimum_zone_circle(points)
    ls = roundness(points, "least_squares")
    # the MZ width is the minimum of the very quantity LS reports at its own centre: never larger (rounding only)
    assert zone.width <= ls + 1e-12
    # and no nearby centre does better (a local minimum of the exact objective), probed at 1/10 of the width away
    step = 0.1 * max(zone.width, 1e-9)
    for direction in np.column_stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)]):
        assert zone_width_at(points, zone.center + step * direction) >= zone.width - 1e-12


def test_roundness_refuses_bad_input():
    with pytest.raises(ValueError, match="shape"):
        roundness(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="NaN"):
        roundness(np.array([[0, 1], [1, 0], [np.nan, 0], [0, -1]], float))
    with pytest.raises(ValueError, match="line"):
        fit_circle_least_squares(np.column_stack([np.arange(5.0), 2 * np.arange(5.0)]))
    with pytest.raises(ValueError, match="method"):
        roundness(profile(np.full(THETA.size, R)), method="chebyshev")


# -------------------------------------------------------------------------------------------------------------- cone

def cone_points(apex, axis, half_angle, h_range, n, rng, sector=(0.0, 2 * np.pi)):
    """Points on a cone: at distance h from the apex along the unit axis, radius h tan(half_angle)."""
    axis = axis / np.linalg.norm(axis)
    e1 = np.cross([0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0], axis)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    h = rng.uniform(*h_range, n)
    phi = rng.uniform(*sector, n)
    radial = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    return apex + h[:, None] * axis + (h * np.tan(half_angle))[:, None] * radial


def nas979_cone():
    """NAS 979 defaults (DESIGN.md §6): half angle 15 deg, axis tilted 10 deg about Y, base diameter 80 mm at the
    origin, height 20 mm; the radius shrinks upward, so the apex lies above the base at 40 / tan 15 deg."""
    half_angle = np.radians(15.0)
    up = np.array([np.sin(np.radians(10.0)), 0.0, np.cos(np.radians(10.0))])
    apex = (40.0 / np.tan(half_angle)) * up
    return apex, -up, half_angle  # axis from the apex into the cone: down


def assert_cone(fit: ConeFit, apex, axis, half_angle, tol):
    assert abs(fit.half_angle_rad - half_angle) < tol
    np.testing.assert_allclose(fit.axis, axis, atol=tol)
    np.testing.assert_allclose(fit.apex, apex, atol=tol * np.linalg.norm(apex) + tol)


def test_cone_fit_recovers_the_nas979_cone_exactly():
    rng = np.random.default_rng(1)
    apex, axis, half_angle = nas979_cone()
    slant = np.linalg.norm(apex)
    # heights from the apex: 20 mm of frustum above the base, measured along the axis
    points = cone_points(apex, axis, half_angle, (slant - 20.0, slant), 2000, rng)
    up = -axis
    fit = fit_cone(points, reference_plane=(np.zeros(3), up))
    assert_cone(fit, apex, axis, half_angle, 1e-9)
    np.testing.assert_allclose(fit.axis_point, np.zeros(3), atol=1e-9)  # the base centre
    assert abs(fit.radius_at_axis_point - 40.0) < 1e-9
    assert fit.rms < 1e-10


def test_cone_fit_recovers_a_rotated_translated_partial_cone_from_a_rough_start():
    rng = np.random.default_rng(2)
    rotation = Rotation.from_rotvec([0.4, -0.9, 1.3])
    apex = np.array([120.0, -35.0, 60.0])
    axis = rotation.apply([0.0, 0.0, 1.0])
    half_angle = np.radians(32.0)
    points = cone_points(apex, axis, half_angle, (30.0, 70.0), 1500, rng, sector=(0.3, 3.5))  # 183 degree sector
    rough = rotation.apply(Rotation.from_rotvec([0.05, -0.04, 0.0]).apply([0.0, 0.0, -1.0]))  # 3.7 deg off, flipped
    fit = fit_cone(points, initial_axis=rough, initial_apex=apex + [3.0, -2.0, 4.0])
    assert_cone(fit, apex, axis, half_angle, 1e-9)
    # no start at all: the principal directions are tried
    assert_cone(fit_cone(points), apex, axis, half_angle, 1e-9)


def test_cone_fit_recovers_a_slight_taper_with_a_far_apex():
    # a 1:50 taper on a shaft (half angle 0.57 deg): the apex is 2.5 m away. The parameterisation carries the radius on
    # a plane near the points, not the apex, so the fit is as exact; the apex inherits an error scaled by 1/tan.
    rng = np.random.default_rng(3)
    half_angle = np.arctan(0.01)
    axis = np.array([1.0, 0.0, 0.0])
    apex = np.array([-2500.0, 10.0, 5.0])
    points = cone_points(apex, axis, half_angle, (2500.0, 2600.0), 2000, rng)  # radius 25 to 26 mm
    fit = fit_cone(points, initial_axis=axis)
    assert abs(fit.half_angle_rad - half_angle) < 1e-12
    np.testing.assert_allclose(fit.axis, axis, atol=1e-12)
    np.testing.assert_allclose(fit.apex, apex, atol=1e-9 / np.tan(half_angle))
    assert fit.rms < 1e-10



def test_points_on_one_ring_do_not_determine_a_cone_and_its_error_amplification_says_so():
    """Every cone through a circle fits points on that circle: the fit's Jacobian is rank-deficient and its standard
    errors (from residuals near zero) say nothing. The error amplification (the largest move of the cone per unit
    RMS error of the points, angles as displacements at the cloud's size) tells the cases apart, and is scale-free."""
    rng = np.random.default_rng(11)
    apex, axis, half_angle = nas979_cone()
    slant = np.linalg.norm(apex)
    full = cone_points(apex, axis, half_angle, (slant - 20.0, slant), 3000, rng)
    fit = fit_cone(full, initial_axis=axis)
    assert 3.0 < fit.error_amplification < 30.0  # the whole height and turn: about 10
    # ten times the part, the same shape: the same number (it measures geometry, not millimetres)
    assert fit_cone(10.0 * full, initial_axis=axis).error_amplification == pytest.approx(fit.error_amplification,
                                                                                         rel=1e-6)
    band = cone_points(apex, axis, half_angle, (slant - 11.0, slant - 9.0), 1000, rng)  # a 2 mm band
    assert 30.0 < fit_cone(band, initial_axis=axis).error_amplification < 200.0
    ring = cone_points(apex, axis, half_angle, (slant - 10.0, slant - 10.0), 12, rng)
    for points in (ring, ring + rng.normal(0.0, 0.001, ring.shape), ring + rng.normal(0.0, 0.01, ring.shape)):
        # exactly on one ring, or with 1 um or 10 um of noise: above the 1000 at which inspect stops evaluating it
        assert fit_cone(points, initial_axis=axis).error_amplification > 2000.0

def cone_second_formulation(points, apex0, axis0, half_angle0):
    """Second formulation of the cone fit: the same objective (sum of squared orthogonal distances) written from the
    apex with the axis in spherical angles, solved by scipy's trust-region-reflective method with a finite-difference
    Jacobian (the fit under test: Levenberg-Marquardt, analytic Jacobian, axis-point/radius parameters), from a start
    away from the first fit. Returns ((apex, axis, half angle), sum of squares)."""
    def unpack(x):
        polar, azimuth = x[3], x[4]
        axis = np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
        return x[:3], axis, x[5]

    def distances(x):
        apex, axis, alpha = unpack(x)
        w = points - apex
        h = w @ axis
        r = np.linalg.norm(w - h[:, None] * axis, axis=1)
        return r * np.cos(alpha) - h * np.sin(alpha)  # distance to the generator r = h tan(alpha)

    x0 = np.r_[apex0, np.arccos(axis0[2]), np.arctan2(axis0[1], axis0[0]), half_angle0]
    result = least_squares(distances, x0, method="trf", jac="3-point", x_scale="jac", xtol=1e-15, ftol=1e-15,
                           gtol=1e-15)
    return unpack(result.x), 2.0 * result.cost


def test_cone_fit_with_noise_is_within_its_standard_errors_and_agrees_with_a_second_formulation():
    rng = np.random.default_rng(4)
    apex, axis, half_angle = nas979_cone()
    slant = np.linalg.norm(apex)
    noise = 0.001  # mm, 1 um probe noise
    exact = cone_points(apex, axis, half_angle, (slant - 20.0, slant), 3000, rng)
    points = exact + rng.normal(0.0, noise, exact.shape)
    fit = fit_cone(points, reference_plane=(np.zeros(3), -axis))
    # the residual RMS is the noise along the surface normal: noise * sqrt((n - 6) / n), within a few percent for n=3000
    assert abs(fit.rms - noise) < 0.05 * noise
    # errors within 4 standard errors (two-sided 4 sigma: 6e-5 chance of a false alarm per check, and the seed is
    # fixed); the axis and position errors are 2D, their std the root sum of both variances, so 4 of those is generous
    angle_error = np.arccos(np.clip(fit.axis @ axis, -1, 1))
    assert abs(fit.half_angle_rad - half_angle) < 4 * fit.half_angle_std_rad
    assert angle_error < 4 * fit.axis_std_rad
    assert np.linalg.norm(fit.axis_point) < 4 * fit.axis_point_std_mm
    # the standard errors themselves have the size expected for 1 um noise on 3000 points: well under 1e-4
    assert fit.half_angle_std_rad < 1e-4 and fit.axis_std_rad < 1e-4 and fit.axis_point_std_mm < 1e-3

    # second formulation from the nominal cone moved off (the first fit is not its start)
    (apex2, axis2, alpha2), cost2 = cone_second_formulation(points, apex + [0.5, -0.3, 0.2],
                                                            Rotation.from_rotvec([0.01, 0.02, 0]).apply(axis),
                                                            half_angle + 0.005)
    cost1 = float(fit.residuals @ fit.residuals)
    # both reach the same minimum of the sum of squares, to its rounding (1e-16 relative, times a margin)
    assert abs(cost1 - cost2) < 1e-12 * cost1
    # A parameter k standard errors from the minimum raises the sum of squares by k^2 sigma^2, out of n sigma^2:
    # with the cost known to ~1e-16 relative, k ~ sqrt(1e-16 n) ~ 5e-7 is the most two exact solvers can differ by.
    # Allow 1e-5 standard errors (measured: ~1e-9 for the half angle, ~1e-7 for the apex).
    assert abs(alpha2 - fit.half_angle_rad) < 1e-5 * fit.half_angle_std_rad
    assert np.arccos(np.clip(axis2 @ fit.axis, -1, 1)) < 1e-5 * fit.axis_std_rad
    # the apex sits 1/tan(alpha) radii out along the axis: its standard error is the axis point's over tan(alpha)
    assert np.linalg.norm(apex2 - fit.apex) < 1e-5 * fit.axis_point_std_mm / np.tan(half_angle)


def test_section_ring_of_a_cone_is_round_at_the_expected_radius():
    rng = np.random.default_rng(5)
    apex, axis, half_angle = nas979_cone()
    slant = np.linalg.norm(apex)
    points = cone_points(apex, axis, half_angle, (slant - 20.0, slant), 20000, rng)
    up = -axis
    tolerance = 0.25
    ring, index = section_ring(points, np.zeros(3), up, 10.0, tolerance, half_angle_rad=-half_angle,
                               return_index=True)
    assert len(ring) > 100 and np.all(np.abs((points[index]) @ up - 10.0) <= tolerance)
    # moved along the generators onto the section plane: a circle of radius 40 - 10 tan 15deg about the axis
    fit = fit_circle_least_squares(ring)
    np.testing.assert_allclose(fit.center, 0.0, atol=1e-9)
    assert abs(fit.radius - (40.0 - 10.0 * np.tan(half_angle))) < 1e-9
    assert roundness(ring, "minimum_zone") < 1e-9
    # without the correction the slab's radial spread shows: the zone about the true centre is 2 tolerance tan(half
    # angle) wide, so the minimum zone is at most that (the LS value may exceed it: its centre chases the scatter)
    raw = section_ring(points, np.zeros(3), up, 10.0, tolerance)
    assert 1.5 * tolerance * np.tan(half_angle) < roundness(raw, "minimum_zone") <= 2 * tolerance * np.tan(half_angle) + 1e-9


# -------------------------------------------------------------------------------------------- planes, lines, zones

def test_plane_and_line_fits_recover_known_geometry():
    rng = np.random.default_rng(6)
    normal = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    in_plane = np.linalg.svd(normal[None, :])[2][1:]  # two unit vectors orthogonal to the normal
    point = np.array([5.0, 6.0, 7.0])
    plane_points = point + rng.uniform(-50, 50, (500, 2)) @ in_plane
    fit = fit_plane(plane_points)
    np.testing.assert_allclose(fit.normal, normal, atol=1e-12)
    assert np.abs((fit.point - point) @ normal) < 1e-10 and np.abs(fit.residuals).max() < 1e-10

    direction = np.array([3.0, -1.0, 2.0]) / np.linalg.norm([3.0, -1.0, 2.0])
    line = fit_line(point + rng.uniform(-80, 80, 300)[:, None] * direction)
    np.testing.assert_allclose(line.direction, direction, atol=1e-12)
    assert np.abs(line.residuals).max() < 1e-10


def test_straightness_of_a_cosine_profile_is_twice_the_amplitude_with_both_methods():
    # y = e cos(2π x / L) over one period: cov(x, y) = 0, so the LS line is y = mean(y) exactly and the deviations' PV
    # is 2e; the convex hull is nearly the triangle (0, e), (L, e), (L/2, -e), whose least altitude is 2e.
    e, length = 0.004, 100.0
    x = np.linspace(0.0, length, 1001)
    points = np.column_stack([x, 7.0 + e * np.cos(2 * np.pi * x / length)])
    assert abs(straightness(points, method="least_squares") - 2 * e) < 1e-10
    assert abs(straightness(points, method="minimum_zone") - 2 * e) < 1e-10
    # 3D, least squares: the diameter of the cylinder about the LS line holding all points. A straight line gives 0.
    # Offsets of +-3 um at the two ends (t = -+50 mm from the centroid), perpendicular to the line, tilt the LS line by
    # slope = sum(t offset) / sum(t^2) = 2 * 50 * 0.003 / sum(t^2) towards them, so they lie 0.003 - 50 slope from it
    # (total and ordinary least squares differ at order slope^2, ~1e-13 mm here).
    line3 = np.column_stack([x, 2 * x, -x]) / np.sqrt(6.0)
    assert straightness(line3) < 1e-10
    off = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)  # perpendicular to (1, 2, -1)
    line3[0] += 0.003 * off
    line3[-1] -= 0.003 * off
    t = x - 50.0
    slope = 2 * 50.0 * 0.003 / (t @ t)
    assert abs(straightness(line3) - 2 * (0.003 - 50.0 * slope)) < 1e-10


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 150), slope=st.floats(-2.0, 2.0))
def test_minimum_zone_straightness_is_the_least_width_over_all_directions(seed, n, slope):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 100.0, n)
    points = np.column_stack([x, slope * x + rng.normal(0.0, 0.005, n)])
    mz = straightness(points, method="minimum_zone")
    assert mz <= straightness(points, method="least_squares") + 1e-12

    # second formulation, by brute force without the convex hull: the narrowest zone has one side through two of the
    # points, so try the direction of every pair of points and take the least projected width
    i, j = np.triu_indices(n, 1)
    directions = points[j] - points[i]
    keep = np.linalg.norm(directions, axis=1) > 0
    normals = np.column_stack([-directions[keep, 1], directions[keep, 0]])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    projections = points @ normals.T  # (n, pairs)
    brute = (projections.max(axis=0) - projections.min(axis=0)).min()
    # the same candidate set evaluated two ways: equal to rounding of 100 mm coordinates (1e-14 relative, 1e-12 mm)
    assert abs(mz - brute) < 1e-11

    # and a plain search over the direction angle can only find wider zones (the optimum is a kink of the width
    # function, where an angle search stalls: d(width)/d(angle) is the profile length, 100 mm/rad)
    angles = np.arctan(slope) + np.linspace(-0.01, 0.01, 2001)
    widths = [np.ptp(points @ np.array([-np.sin(a), np.cos(a)])) for a in angles]
    assert mz <= min(widths) + 1e-12


def test_parallelism_of_a_tilted_plane_to_a_datum():
    # z = 0.001 x over x in [0, 100]: 0.1 mm between the two planes parallel to z = 0 that hold it
    rng = np.random.default_rng(8)
    xy = rng.uniform(0.0, 100.0, (400, 2))
    xy[:2, 0] = [0.0, 100.0]  # the extremes present
    toleranced = np.column_stack([xy, 20.0 + 0.001 * xy[:, 0]])
    datum = fit_plane(np.column_stack([xy, np.zeros(len(xy))]))
    assert abs(parallelism(toleranced, datum) - 0.1) < 1e-12
    assert abs(parallelism(toleranced, (np.zeros(3), [0, 0, -2.0])) - 0.1) < 1e-12
    with pytest.raises(ValueError):
        parallelism(toleranced, (np.zeros(3), np.zeros(3)))


# --------------------------------------------------------- sphere, cylinder, 3D circle, minimum-zone plane: exact cases
#
# Each case is built so that the nominal element is the exact answer. Least squares (Gauss): the point set is
# symmetric under a group of rotations about the nominal (the octahedral directions of a sphere, quarter turns and a
# half-height flip of a cylinder, quarter turns of a circle), its deviations sum to zero, so the unique least-squares
# element is the symmetric one: the nominal. Minimum zone (Chebyshev): points at +d and -d whose contact gradients
# hold the origin inside their convex hull (the first-order optimality condition: no move of the element lowers the
# outer contacts and raises the inner ones at once), and every other point strictly inside the band: the zone is the
# nominal, of width 2 d, wherever the other points lie; they are placed asymmetrically so that the least-squares
# start of the Chebyshev solver is away from the answer. Tolerances: 1e-3 um and 1e-3 urad, as the issue asks.

ROT = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()  # a general orientation: no world axis is special
C3 = np.array([12.0, -7.0, 30.0])
D = 0.004  # mm, the form deviation of the constructed cases (+-4 um)
UM, URAD = 1e-6, 1e-9  # 1e-3 um in mm, 1e-3 urad in rad


def _unit_rows(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=1)[:, None]


def _angle(a, b):
    """Angle between two lines (either sign), rad, accurate near zero (|a x b|, not arccos)."""
    return float(np.linalg.norm(np.cross(a / np.linalg.norm(a), b / np.linalg.norm(b))))


_OCTAHEDRON = _unit_rows([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
_CUBE = _unit_rows([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
_OCTA_GROUP = [Rotation.from_matrix(m).as_matrix() for m in Rotation.create_group("O").as_matrix()]


def sphere_case(radius=25.0, symmetric=True, seed=0):
    """Outer contacts (+D) at the 6 octahedron directions, inner (-D) at the 8 cube corners (both sets are orbits of
    the cube's 24 rotations). Symmetric: one more orbit of 24 points at +D / 12, so the deviations sum to 0.
    Asymmetric: 60 random points between -0.3 D and 0.8 D."""
    rng = np.random.default_rng(seed)
    directions = [_OCTAHEDRON, _CUBE]
    deviation = [np.full(6, D), np.full(8, -D)]
    if symmetric:
        seedpoint = _unit_rows(rng.normal(size=(1, 3)))[0]
        orbit = np.array([g @ seedpoint for g in _OCTA_GROUP])
        directions.append(orbit)
        deviation.append(np.full(24, 2 * D / 24))  # 6 D - 8 D + 24 (D / 12) = 0
    else:
        directions.append(_unit_rows(rng.normal(size=(60, 3))))
        deviation.append(rng.uniform(-0.3 * D, 0.8 * D, 60))
    u = np.vstack(directions) @ ROT.T
    return C3 + (radius + np.concatenate(deviation))[:, None] * u, radius


def test_least_squares_sphere_is_the_nominal_of_a_symmetric_case():
    from trueaxis.inspect.form import fit_sphere

    points, radius = sphere_case()
    fit = fit_sphere(points)
    assert np.abs(fit.center - C3).max() < UM and abs(fit.radius - radius) < UM
    np.testing.assert_allclose(fit.residuals, np.linalg.norm(points - fit.center, axis=1) - fit.radius, atol=1e-12)


@pytest.mark.parametrize("symmetric", [True, False])
def test_minimum_zone_sphere_is_the_nominal_zone(symmetric):
    from trueaxis.inspect.form import fit_sphere, minimum_zone_sphere

    points, radius = sphere_case(symmetric=symmetric)
    zone = minimum_zone_sphere(points)
    assert np.abs(zone.center - C3).max() < UM
    assert abs(zone.width - 2 * D) < UM and abs(zone.radius_inner - (radius - D)) < UM
    if not symmetric:  # the least-squares start was away from the answer, and the zone is never wider
        assert np.abs(fit_sphere(points).center - C3).max() > 100 * UM
        ls = fit_sphere(points).residuals
        assert zone.width <= np.ptp(ls) + 1e-12


def plane_case(symmetric=True, seed=1):
    """Outer contacts (+D) at (+-a, 0), inner (-D) at (0, +-a) of the plane's own frame: the segments cross, the
    zone is the nominal plane. Symmetric: other points in pairs (x, y), (-x, -y) with the same deviation summing to
    0 (the least-squares plane through the centroid with zero moments is the nominal)."""
    rng = np.random.default_rng(seed)
    a = 20.0
    xy = [np.array([[a, 0], [-a, 0], [0, a], [0, -a]])]
    dev = [np.array([D, D, -D, -D])]
    if symmetric:
        extra = rng.uniform(-a, a, (30, 2))
        e = rng.uniform(-0.8 * D, 0.8 * D, 30)
        e -= e.mean()
        xy += [extra, -extra]
        dev += [e, e]
    else:
        xy.append(rng.uniform(-a, a, (80, 2)))
        dev.append(rng.uniform(-0.3 * D, 0.8 * D, 80))
    xy, dev = np.vstack(xy), np.concatenate(dev)
    return C3 + xy[:, :1] * ROT[:, 0] + xy[:, 1:] * ROT[:, 1] + dev[:, None] * ROT[:, 2]


@pytest.mark.parametrize("symmetric", [True, False])
def test_minimum_zone_plane_is_the_nominal_zone(symmetric):
    from trueaxis.inspect.form import minimum_zone_plane

    points = plane_case(symmetric)
    zone = minimum_zone_plane(points)
    assert _angle(zone.normal, ROT[:, 2]) < URAD
    assert abs(zone.width - 2 * D) < UM and abs((zone.point - C3) @ ROT[:, 2]) < UM
    ls = fit_plane(points)
    if symmetric:
        assert _angle(ls.normal, ROT[:, 2]) < URAD and abs((ls.point - C3) @ ROT[:, 2]) < UM
    else:
        assert _angle(ls.normal, ROT[:, 2]) > 1000 * URAD  # the solver had to move
    assert zone.width <= np.ptp(ls.residuals) + 1e-12
    np.testing.assert_allclose(np.abs(zone.residuals).max(), D, atol=UM)


def cylinder_case(radius=15.0, symmetric=True, seed=2):
    """Outer contacts (+D) at 0, 90, 180, 270 deg and inner (-D) at 45, 135, 225, 315 deg, each at heights +-H.
    Symmetric: other points in quadruples (theta, +-h), (theta + 180, +-h) with one deviation, summing to 0."""
    rng = np.random.default_rng(seed)
    big_h = 30.0
    q = np.radians([0, 90, 180, 270])
    theta = [np.tile(q, 2), np.tile(q + np.pi / 4, 2)]
    height = [np.repeat([big_h, -big_h], 4)] * 2
    dev = [np.full(8, D), np.full(8, -D)]
    if symmetric:
        t, h = rng.uniform(0, np.pi, 10), rng.uniform(-big_h, big_h, 10)
        e = rng.uniform(-0.8 * D, 0.8 * D, 10)
        e -= e.mean()
        theta += [t, t + np.pi, t, t + np.pi]
        height += [h, h, -h, -h]
        dev += [e] * 4
    else:
        theta.append(rng.uniform(0, 2 * np.pi, 100))
        height.append(rng.uniform(-big_h, big_h, 100))
        dev.append(rng.uniform(-0.2 * D, 0.8 * D, 100))
    theta, height, dev = (np.concatenate(v) for v in (theta, height, dev))
    local = np.column_stack([(radius + dev) * np.cos(theta), (radius + dev) * np.sin(theta), height])
    return C3 + local @ ROT.T, radius


@pytest.mark.parametrize("symmetric", [True, False])
def test_cylinder_fits_are_the_nominal(symmetric):
    from trueaxis.inspect.form import fit_cylinder, minimum_zone_cylinder

    points, radius = cylinder_case(symmetric=symmetric)
    axis = ROT[:, 2]

    def off_axis(point):
        w = point - C3
        return np.linalg.norm(w - (w @ axis) * axis)

    ls = fit_cylinder(points)
    if symmetric:
        assert _angle(ls.axis, axis) < URAD and off_axis(ls.axis_point) < UM and abs(ls.radius - radius) < UM
    else:
        assert _angle(ls.axis, axis) > 1000 * URAD
    zone = minimum_zone_cylinder(points)
    assert _angle(zone.axis, axis) < URAD and off_axis(zone.axis_point) < UM
    assert abs(zone.width - 2 * D) < UM and abs(zone.radius_outer - (radius + D)) < UM
    assert zone.width <= np.ptp(ls.residuals) + 1e-12


def test_least_squares_circle_in_space_is_the_nominal_of_a_symmetric_case():
    from trueaxis.inspect.form import fit_circle_3d

    radius = 20.0
    theta = np.radians(np.arange(0, 360, 15.0))  # 24 points: invariant under quarter turns about the axis
    k = np.arange(24) % 6
    radial = np.select([k == 0, k == 3], [D, -D], 0.0)           # +D at 0, 90, ... deg, -D at 45, 135, ...
    normal = np.select([k == 1, k == 2, k == 4, k == 5], [D, -D, D, -D], 0.0)  # out of plane, +-D
    local = np.column_stack([(radius + radial) * np.cos(theta), (radius + radial) * np.sin(theta), normal])
    points = C3 + local @ ROT.T
    fit = fit_circle_3d(points)
    assert _angle(fit.normal, ROT[:, 2]) < URAD
    assert np.abs(fit.center - C3).max() < UM and abs(fit.radius - radius) < UM
    np.testing.assert_allclose(fit.normal_residuals * np.sign(fit.normal @ ROT[:, 2]), normal, atol=UM)
    np.testing.assert_allclose(fit.radial_residuals, radial, atol=UM)


# ------------------------------------------------------------------------------- large clouds: the fast paths are exact

def test_cone_fit_of_a_large_cloud_is_the_least_squares_cone_of_all_its_points():
    # more points than the coarse sample: the coarse fit sees every second point, the polish all of them; the second
    # formulation (apex + spherical angles, finite differences, trust region) on all points must reach the same cost
    rng = np.random.default_rng(14)
    apex, axis, half_angle = nas979_cone()
    slant = np.linalg.norm(apex)
    exact = cone_points(apex, axis, half_angle, (slant - 20.0, slant), 30_000, rng)
    points = exact + rng.normal(0.0, 0.002, exact.shape)
    fit = fit_cone(points)  # no start axis: the quadric estimate
    (apex2, axis2, alpha2), cost2 = cone_second_formulation(points, apex + [0.3, -0.2, 0.1],
                                                            Rotation.from_rotvec([0.01, 0.0, 0.01]).apply(axis),
                                                            half_angle + 0.003)
    cost1 = float(fit.residuals @ fit.residuals)
    assert abs(cost1 - cost2) < 1e-12 * cost1
    assert abs(alpha2 - fit.half_angle_rad) < 1e-4 * fit.half_angle_std_rad
    assert np.arccos(np.clip(abs(axis2 @ fit.axis), -1, 1)) < 1e-4 * fit.axis_std_rad


def test_minimum_zone_circle_on_extreme_points_is_the_minimum_over_all_points():
    # 30,000 points: each linear program holds only the 1500 largest and smallest radii; the exact objective over all
    # points, minimised by Nelder-Mead from the result and from the least-squares centre, finds nothing lower
    rng = np.random.default_rng(15)
    theta = rng.uniform(0, 2 * np.pi, 30_000)
    radius = R + 0.004 * np.cos(3 * theta + 0.3) + 0.002 * np.sin(5 * theta) + rng.normal(0, 0.0005, theta.size)
    points = profile(radius, theta=theta)
    zone = minimum_zone_circle(points)
    assert zone.width == pytest.approx(zone_width_at(points, zone.center), abs=1e-15)
    best = nelder_mead_minimum_zone(points, [zone.center, fit_circle_least_squares(points).center])
    assert zone.width <= best.fun + 1e-9  # 1e-3 um
    assert zone.width < np.ptp(fit_circle_least_squares(points).residuals)


def test_least_squares_sphere_cylinder_and_circle_in_space_agree_with_a_second_formulation():
    # asymmetric clouds (no exact answer known): the same objectives written independently (centre / axis in
    # spherical angles, finite-difference Jacobians, trust region) must reach the same minimum
    from trueaxis.inspect.form import fit_circle_3d, fit_cylinder, fit_sphere

    sphere_points, _ = sphere_case(symmetric=False)
    fit = fit_sphere(sphere_points)
    second = least_squares(lambda x: np.linalg.norm(sphere_points - x[:3], axis=1) - x[3],
                           np.r_[C3 + [0.3, -0.2, 0.1], 24.0], method="trf", jac="3-point", xtol=1e-15, ftol=1e-15,
                           gtol=1e-15)
    assert np.abs(second.x[:3] - fit.center).max() < UM and abs(second.x[3] - fit.radius) < UM

    def axis_of(polar, azimuth):
        return np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])

    cylinder_points, _ = cylinder_case(symmetric=False)
    fit = fit_cylinder(cylinder_points)

    def cylinder_residuals(x):
        axis = axis_of(x[3], x[4])
        w = cylinder_points - x[:3]
        return np.linalg.norm(w - np.outer(w @ axis, axis), axis=1) - x[5]

    start_axis = Rotation.from_rotvec([0.02, -0.01, 0.0]).apply(ROT[:, 2])
    x0 = np.r_[C3 + [0.2, 0.1, 0.0], np.arccos(start_axis[2]), np.arctan2(start_axis[1], start_axis[0]), 14.9]
    second = least_squares(cylinder_residuals, x0, method="trf", jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    axis2 = axis_of(second.x[3], second.x[4])
    assert _angle(axis2, fit.axis) < URAD and abs(second.x[5] - fit.radius) < UM
    w = second.x[:3] - fit.axis_point
    assert np.linalg.norm(w - (w @ fit.axis) * fit.axis) < UM
    assert abs(float(fit.residuals @ fit.residuals) - 2 * second.cost) < 1e-12 * float(fit.residuals @ fit.residuals)

    rng = np.random.default_rng(21)
    theta = np.sort(rng.uniform(0, 2 * np.pi, 40))
    local = np.column_stack([(20 + rng.uniform(-D, D, 40)) * np.cos(theta), (20 + rng.uniform(-D, D, 40))
                             * np.sin(theta), rng.uniform(-D, D, 40) + 0.002 * np.cos(theta)])
    circle_points = C3 + local @ ROT.T
    fit = fit_circle_3d(circle_points)

    def circle_residuals(x):
        normal = axis_of(x[3], x[4])
        w = circle_points - x[:3]
        z = w @ normal
        return np.r_[z, np.linalg.norm(w - np.outer(z, normal), axis=1) - x[5]]

    start_normal = Rotation.from_rotvec([0.01, 0.02, 0.0]).apply(ROT[:, 2])
    x0 = np.r_[C3 + [0.1, -0.1, 0.05], np.arccos(start_normal[2]), np.arctan2(start_normal[1], start_normal[0]), 19.9]
    second = least_squares(circle_residuals, x0, method="trf", jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert _angle(axis_of(second.x[3], second.x[4]), fit.normal) < URAD
    assert np.abs(second.x[:3] - fit.center).max() < UM and abs(second.x[5] - fit.radius) < UM


def test_zone_linear_program_matches_highs_on_random_and_degenerate_programs():
    """The hand-written simplex of the minimum-zone steps against scipy's HiGHS: the same optimal zone (to rounding
    of the optimum, 1e-11 relative), and its x feasible with the zone it reports; rounded data make ties and
    degenerate vertices."""
    from scipy.optimize import linprog

    rng = np.random.default_rng(0)
    for trial in range(150):
        k, m = int(rng.integers(1, 6)), int(rng.integers(3, 300))
        slopes = rng.normal(size=(m, k))
        values = rng.normal(size=m)
        if trial % 3 == 0:
            slopes, values = np.round(slopes, 1), np.round(values, 1)
        bound = float(rng.choice([1e-3, 0.1, 1.0, 10.0]))
        x, zone = form._zone_linear_program(slopes, values, bound)
        assert np.all(np.abs(x) <= bound * (1 + 1e-12))
        assert abs(np.ptp(values + slopes @ x) - zone) <= 1e-11 * max(1.0, zone)
        upper = np.column_stack([slopes, -np.ones(m), np.zeros(m)])
        lower = np.column_stack([-slopes, np.zeros(m), np.ones(m)])
        highs = linprog(c=np.r_[np.zeros(k), 1.0, -1.0], A_ub=np.vstack([upper, lower]), b_ub=np.r_[-values, values],
                        bounds=[(-bound, bound)] * k + [(None, None)] * 2, method="highs",
                        options=dict(primal_feasibility_tolerance=1e-10, dual_feasibility_tolerance=1e-10))
        assert highs.status == 0
        assert zone == pytest.approx(highs.fun, rel=1e-11, abs=1e-11)


def test_inspection_imports_neither_scipy_nor_numba():
    """The inspection's own path (deviations, fits, point files) starts without scipy.optimize (0.45 s) or numba
    (its kernels compiled ahead of time by trueaxis.warm, when they were built)."""
    import subprocess
    import sys

    from trueaxis.compiled import aot_available

    code = ("import sys, numpy as np\n"
            "from trueaxis.inspect import form, report, cloud\n"
            "t = np.linspace(0, 6.28, 400)\n"
            "p = np.column_stack([(40 - np.tile([1.0, 9.0], 200) * 0.27) * np.cos(t), "
            "(40 - np.tile([1.0, 9.0], 200) * 0.27) * np.sin(t), np.tile([1.0, 9.0], 200)])\n"
            "form.fit_cone(p, initial_axis=[0, 0, 1])\n"
            "form.minimum_zone_circle(p[:, :2])\n"
            "print('scipy.optimize' in sys.modules, 'numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "False"
    if aot_available():
        assert out[1] == "False"


def test_cone_normal_equations_match_the_numpy_jacobian_and_finite_differences():
    """The compiled pass (trueaxis.inspect.kernels) against the numpy Jacobian of the same model, and that Jacobian
    against central differences of the residuals: J^T J, J^T f and f agree to rounding."""
    rng = np.random.default_rng(3)
    axis0 = np.array([np.sin(0.17), 0.0, np.cos(0.17)])
    e1, e2 = form._perpendicular_basis(axis0)
    h, th = rng.uniform(0.0, 20.0, 2000), rng.uniform(0.0, 2 * np.pi, 2000)
    radius = 40.0 - h * np.tan(np.radians(15.0)) + rng.normal(0, 0.01, 2000)
    points = h[:, None] * axis0 + radius[:, None] * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    unpack, residuals, jacobian, normal_equations = form._cone_model(points, axis0, np.zeros(3))
    params = np.array([1e-3, -2e-3, 0.05, -0.02, 40.01, np.radians(15.2)])
    normal, gradient, f, cost = normal_equations(params)
    jac = jacobian(params)
    np.testing.assert_allclose(f, residuals(params), rtol=0, atol=1e-13)
    assert cost == pytest.approx(f @ f, rel=1e-12)
    np.testing.assert_allclose(normal, jac.T @ jac, rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(gradient, jac.T @ f, rtol=1e-9, atol=1e-11)
    step = 1e-6
    numeric = np.column_stack([(residuals(params + step * e) - residuals(params - step * e)) / (2 * step)
                               for e in np.eye(6)])
    np.testing.assert_allclose(jac, numeric, rtol=0, atol=1e-7)
