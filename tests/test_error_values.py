"""The compiled error values (``ErrorFunction.value_and_derivative``, ``error_kernel``) against the reference evaluation
(``__call__``, ``derivative``, ``basis``), against central differences, and as the twin packs them."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import random_poses
from test_chain_kernel import every_parameter_non_zero, load
from trueaxis.machine import ErrorTwin
from trueaxis.machine.error_functions import fourier_series, legendre_series, table
from trueaxis.machine.model import ERROR_DIRECTIONS
from trueaxis.resources import machine_files

RTOL = 1e-12


def _knots(rng, lo, hi, n):
    """n increasing, unevenly spaced positions from lo to hi."""
    inner = np.sort(rng.uniform(lo, hi, n - 2))
    return np.concatenate([[lo], inner, [hi]])


def functions():
    """One function of each kind and variant: (id, function, (lo, hi) the range it is defined over)."""
    rng = np.random.default_rng(3)
    out = []
    for interp in ("linear", "cubic"):
        at = _knots(rng, -300.0, 100.0, 9)
        out.append((f"{interp}", table(at, rng.normal(0, 10, 9), interp), (at[0], at[-1])))
        at = np.radians(np.linspace(-120.0, 30.0, 11))
        out.append((f"{interp}-rotary", table(at, rng.normal(0, 10, 11), interp, label_unit="deg"), (at[0], at[-1])))
        # A full turn: the last node is the first one a turn later. As read from a file (last value = first) and as
        # the identifier or with_parameters may leave it (last value free, unused).
        at = np.radians(np.linspace(0.0, 360.0, 13))
        v = rng.normal(0, 10, 13)
        v_file = v.copy()
        v_file[-1] = v_file[0]
        out.append((f"{interp}-periodic", table(at, v_file, interp, periodic=True, label_unit="deg"), (at[0], at[-1])))
        out.append((f"{interp}-periodic-free-last", table(at, v, interp, periodic=True, label_unit="deg"),
                    (at[0], at[-1])))
    for size in (1, 2, 3, 5):
        out.append((f"legendre-{size}", legendre_series(rng.normal(0, 10, size), (-150.0, 250.0)), (-150.0, 250.0)))
    out.append(("fourier", fourier_series([[1, 3.0, -2.0], [2, 1.5, 0.5], [4, -0.3, 0.8]]), (-2 * np.pi, 2 * np.pi)))
    out.append(("fourier-fractional", fourier_series([[0.5, 2.0, 1.0], [3, -1.0, 0.25]]), (-2 * np.pi, 2 * np.pi)))
    return out


FUNCTIONS = functions()


def positions(fn, lo, hi, n=3000, seed=5):
    """Random positions over the range and a fifth beyond it on each side, the table nodes and the ends exactly, and
    for periodic tables the same positions turns away."""
    rng = np.random.default_rng(seed)
    w = hi - lo
    q = np.concatenate([rng.uniform(lo - 0.2 * w, hi + 0.2 * w, n), [lo, hi], [] if fn.at is None else fn.at])
    if fn.periodic:
        q = np.concatenate([q, q + 2 * np.pi, q - 6 * np.pi])
    return q


@pytest.mark.parametrize("name, fn, span", FUNCTIONS, ids=[f[0] for f in FUNCTIONS])
def test_compiled_values_and_derivatives_equal_the_reference(name, fn, span):
    q = positions(fn, *span)
    v, dv = fn.value_and_derivative(q)
    v_ref, dv_ref = fn(q), fn.derivative(q)
    # Relative to the function's size (a value near one of its zeros has no relative accuracy of its own).
    np.testing.assert_allclose(v, v_ref, rtol=0, atol=RTOL * np.abs(v_ref).max())
    np.testing.assert_allclose(dv, dv_ref, rtol=0, atol=RTOL * max(np.abs(dv_ref).max(), 1e-300))
    # Held value, zero slope outside a table or a Legendre domain.
    if fn.kind != "fourier" and not fn.periodic:
        out = (q < span[0]) | (q > span[1])
        assert np.all(dv[out] == 0.0)
        np.testing.assert_array_equal(v[q < span[0]], fn(np.array([span[0]])).repeat((q < span[0]).sum()))
    # The basis gives the same function (value and slope): what the parameter Jacobian and the identifier rely on.
    np.testing.assert_allclose(fn.basis(q) @ fn.values, v_ref, rtol=0, atol=1e-12 * np.abs(v_ref).max())
    np.testing.assert_allclose(fn.basis_derivative(q) @ fn.values, dv_ref, rtol=0,
                               atol=1e-12 * max(np.abs(dv_ref).max(), 1e-300))


def test_compiled_values_keep_the_shape_of_q():
    fn = FUNCTIONS[0][1]
    q = np.linspace(-250.0, 50.0, 12).reshape(3, 4)
    v, dv = fn.value_and_derivative(q)
    assert v.shape == dv.shape == (3, 4)
    np.testing.assert_array_equal(v, fn(q))
    v0, dv0 = fn.value_and_derivative(-100.0)
    assert np.shape(v0) == () and v0 == fn(np.array([-100.0]))[0]


@pytest.mark.parametrize("name, fn, span", FUNCTIONS, ids=[f[0] for f in FUNCTIONS])
def test_compiled_derivative_matches_central_differences(name, fn, span):
    lo, hi = span
    w = hi - lo
    h = 1e-6 * w
    q = positions(fn, lo, hi, n=500, seed=7)
    if fn.at is not None:
        # Linear tables have a kink at each node, and every table at its ends: stay clear of them by more than h.
        nodes = fn.at if not fn.periodic else np.concatenate([fn.at + 2 * np.pi * k for k in range(-4, 3)])
        q = q[np.min(np.abs(q[:, None] - nodes[None, :]), axis=1) > 10 * h]
    elif fn.kind == "legendre":
        q = q[(np.abs(q - lo) > 10 * h) & (np.abs(q - hi) > 10 * h)]
    v, dv = fn.value_and_derivative(q)
    fd = (fn.value_and_derivative(q + h)[0] - fn.value_and_derivative(q - h)[0]) / (2 * h)
    # Truncation h^2 |f'''| / 6 and round-off 1e-16 |f| / h, both well under 1e-6 of the slope's scale here.
    scale = max(np.abs(dv).max(), np.abs(v).max() / w)
    np.testing.assert_allclose(dv, fd, rtol=0, atol=1e-6 * scale)


def test_periodic_linear_table_ignores_its_last_value():
    # The last node of a full-turn table is its first one a turn later: value, slope and basis all use the first
    # value there (the last one is not a free parameter of the model).
    at = np.radians(np.linspace(0.0, 360.0, 7))
    v = np.array([1.0, 2.0, -1.0, 0.5, 3.0, -2.0, 9.0])
    fn = table(at, v, "linear", periodic=True, label_unit="deg")
    folded = v.copy()
    folded[-1] = v[0]
    q = np.random.default_rng(1).uniform(-7.0, 13.0, 500)
    np.testing.assert_allclose(fn(q), table(at, folded, "linear", periodic=True)(q), rtol=0, atol=1e-14)
    np.testing.assert_allclose(fn(q), fn.basis(q) @ v, rtol=0, atol=1e-13)
    assert fn(np.array([2 * np.pi - 1e-12]))[0] == pytest.approx(v[0], abs=1e-9)


@pytest.mark.parametrize("loaded", [False, True], ids=["unloaded", "force"])
@pytest.mark.parametrize("name", [f.stem for f in machine_files()])
def test_twin_component_values_equal_the_reference(name, loaded):
    # The twin's packed evaluation (every link's six components, scaled to mm and rad, blended with a loaded set)
    # against its reference, function by function.
    m = every_parameter_non_zero(name)
    tw = ErrorTwin(m)
    n = 500
    q = random_poses(m, n, seed=21)
    force = load(m, n, seed=22)[0] if loaded else None
    values = tw._chain_values(q, force, None, errors=True, jacobian=True)
    comp, dcomp = values[4], values[6]
    pose_only = tw._chain_values(q, force, None, errors=True, jacobian=False)
    np.testing.assert_array_equal(pose_only[4], comp)
    for k, link in enumerate(tw.links):
        ref, dref, _ = tw._component_values(link, q[:, link.column], force, n)
        for j, d in enumerate(ERROR_DIRECTIONS):
            size = max(np.abs(ref[:, j]).max(), 1e-300)
            dsize = max(np.abs(dref[:, j]).max(), 1e-300)
            msg = f"E{d}{link.axis}"
            np.testing.assert_allclose(comp[k, :, j], ref[:, j], rtol=0, atol=RTOL * size, err_msg=msg)
            np.testing.assert_allclose(dcomp[k, :, j], dref[:, j], rtol=0, atol=RTOL * dsize, err_msg=msg)
