"""The kernels' straight-line elementary functions (render/vecmath.py) against numpy in extended precision.

Each is checked compiled as the kernels use it (inlined into a numba loop with their options), in ulp of the
exactly rounded result, over its whole stated domain and at the edges where its branches meet.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from roigsf_ros.render import vecmath
from roigsf_ros.render.numba_setup import numba_available

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not installed")


def _compiled(fn: Callable[[float], float], fastmath: bool | set[str] = False) -> Callable[[np.ndarray], np.ndarray]:
    """``fn`` inlined into a numba loop over an array, compiled as a kernel helper (``error_model="numpy"``)."""
    import numba

    f = numba.njit(inline="always", error_model="numpy", fastmath=fastmath)(fn)

    @numba.njit(error_model="numpy", fastmath=fastmath)
    def loop(x: np.ndarray, out: np.ndarray) -> None:
        for i in range(x.shape[0]):
            out[i] = f(x[i])

    def run(x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        loop(x, out)
        return out

    return run


def _ulp(got: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|got - exact| in units of the last place of the float64 nearest ``exact`` (long double)."""
    ref = exact.astype(np.float64)
    return np.abs(got.astype(np.longdouble) - exact) / np.spacing(np.abs(ref)).astype(np.longdouble)


def test_acos_unit_within_one_and_a_half_ulp_on_the_whole_domain() -> None:
    rng = np.random.default_rng(0)
    edges = [-1.0, -0.5, 0.5, 1.0, 0.0, -0.0, np.nextafter(0.5, 1), np.nextafter(-0.5, -1), 1e-300, -1e-17]
    x = np.concatenate([np.linspace(-1.0, 1.0, 200_001), rng.uniform(-1, 1, 50_000), 1 - np.geomspace(1e-16, 1, 2001),
                        edges])  # fmt: skip
    for fastmath in (False, {"contract", "nsz", "reassoc", "arcp"}):
        got = _compiled(vecmath.acos_unit, fastmath)(x)
        exact = np.arccos(x.astype(np.longdouble))
        assert float(_ulp(got, exact).max()) <= 1.5, fastmath
    assert vecmath.acos_unit(-1.0) == pytest.approx(np.pi, abs=0) and vecmath.acos_unit(1.0) == 0.0  # plain Python too


def test_exp_nonpositive_within_two_ulp_and_zero_where_exp_is_subnormal() -> None:
    rng = np.random.default_rng(1)
    tiny = 2.2250738585072014e-308  # the smallest normal double; exp(-708.3964...) = tiny
    normal_x = -np.concatenate([np.linspace(0.0, 708.39, 300_001), rng.uniform(0, 40, 50_000), [0.0, 20.0, 20.5]])
    got = _compiled(vecmath.exp_nonpositive)(normal_x)
    exact = np.exp(normal_x.astype(np.longdouble))
    assert float(_ulp(got, exact).max()) <= 2.0
    below = np.array([-708.4, -709.0, -745.0, -746.0, -1e4, -np.inf])
    assert (np.exp(below) < tiny).all()
    np.testing.assert_array_equal(_compiled(vecmath.exp_nonpositive)(below), 0.0)  # flushed, not subnormal


def test_exp_neg_as_the_rasteriser_compiles_it() -> None:
    """The rasteriser's alpha exp, compiled with its kernels' options (their reassociation may undo the two-part
    ln 2 of the range reduction: a few ulp), over the exponents a kept pair can have (-rho / 2 >= -ln 255 > -5.6)
    and beyond."""
    from roigsf_ros.render import rasterize

    rasterize._RASTER_KERNELS["forward"]  # compiles the kernels and their helper (swapped into their module)
    rng = np.random.default_rng(2)
    for lo, tol in ((5.6, 4e-16), (20.0, 2e-15)):
        x = -np.concatenate([np.linspace(0.0, lo, 5601), rng.uniform(0, lo, 2000)])
        got = np.array([rasterize.exp_neg(float(v)) for v in x])
        ref = np.exp(x.astype(np.longdouble))
        assert float(np.max(np.abs(got - ref) / ref)) < tol, lo
    plain = _compiled(vecmath.exp_neg)(-np.linspace(0.0, 20.0, 200_001))  # without fastmath: within 2 ulp
    assert float(_ulp(plain, np.exp(-np.linspace(0.0, 20.0, 200_001, dtype=np.longdouble))).max()) <= 2.0
