"""Elementary functions in straight-line code, for numba kernels whose loops LLVM should vectorise.

Without Intel's SVML (not part of the numba wheels), a call to ``np.exp`` or ``np.arccos`` inside a loop stays a
scalar libm call and keeps the whole loop scalar (in the ROI's per-voxel weights of Eq. 7, libm's arccos was the
largest part of the pass; issue 12). These versions use only arithmetic, ``floor``, ``sqrt`` and selects, so a loop that
calls them (compiled with ``error_model="numpy"`` where it divides by a loaded value: numba's default tests every
divisor, and that branch keeps the loop scalar) becomes vector code. Each is within 2 ulp of the exact value over
its stated domain (``test/test_vecmath.py``) when compiled without reassociation.
They are numba helpers (:class:`~roigsf_ros.render.numba_setup.Kernels` ``helpers``), plain Python otherwise, and
call no other helper: a kernel module's compiled copy then has that module's compile options alone.
"""

from __future__ import annotations

import numpy as np

_LN2_HI = 6.93147180369123816490e-01
"""ln 2 to 32 bits (``k * _LN2_HI`` is exact for ``|k| < 2^11``)."""
_LN2_LO = 1.90821492927058770002e-10
"""ln 2 - _LN2_HI."""


_EXP_TAYLOR = (
    1.6059043836821613e-10,
    2.08767569878681e-09,
    2.505210838544172e-08,
    2.755731922398589e-07,
    2.7557319223985893e-06,
    2.48015873015873e-05,
    0.0001984126984126984,
    0.001388888888888889,
    0.008333333333333333,
    0.041666666666666664,
    0.16666666666666666,
    0.5,
    1.0,
    1.0,
)
"""1/13!, 1/12!, ..., 1/1!, 1/0!: the Taylor polynomial of exp on ``|r| <= ln(2) / 2`` (Horner, highest first)."""


def exp_neg(x: float) -> float:
    """``exp(x)`` for ``-20 <= x <= 0`` (within 2 ulp; a few more where the caller's fastmath reassociates the
    range reduction); the rasteriser's alpha, where every step counts.

    Range reduction ``x = k ln 2 + r``, ``|r| <= ln(2) / 2``, the Taylor polynomial to degree 13, and ``2^k`` from
    the bits of ``-k`` (``k >= -31``).
    """
    kf = np.floor(x * 1.4426950408889634 + 0.5)
    r = (x - kf * _LN2_HI) - kf * _LN2_LO
    p = _EXP_TAYLOR[0]
    for c in _EXP_TAYLOR[1:]:  # unrolled (a constant tuple)
        p = p * r + c
    ki = int(-kf)
    p = p * 0.5 if ki & 1 else p
    p = p * 0.25 if ki & 2 else p
    p = p * 0.0625 if ki & 4 else p
    p = p * 0.00390625 if ki & 8 else p
    p = p * 1.52587890625e-05 if ki & 16 else p
    return p


def exp_nonpositive(x: float) -> float:
    """``exp(x)`` for any ``x <= 0``: within 2 ulp down to -708.39; 0 below, where ``exp`` is subnormal.

    :func:`exp_neg` with every bit of ``-k`` up to 512, for arguments of any size; written out again rather than
    shared, since a helper that calls a helper is bound in this module's globals, which kernels compiled with
    different options share, and the rasteriser's loop should not pay for the five extra selects. Subnormal results
    are flushed to zero because a select computes both of its sides: a subnormal product costs a microcode assist,
    several times the whole call.
    """
    x = x if x > -709.0 else -709.0  # k >= -1023 below (the bits stay within 512 + ... + 1)
    kf = np.floor(x * 1.4426950408889634 + 0.5)
    r = (x - kf * _LN2_HI) - kf * _LN2_LO
    p = _EXP_TAYLOR[0]
    for c in _EXP_TAYLOR[1:]:  # unrolled (a constant tuple)
        p = p * r + c
    ki = int(-kf)
    p = p * 0.5 if ki & 1 else p
    p = p * 0.25 if ki & 2 else p
    p = p * 0.0625 if ki & 4 else p
    p = p * 0.00390625 if ki & 8 else p
    p = p * 1.52587890625e-05 if ki & 16 else p
    p = p * 2.3283064365386963e-10 if ki & 32 else p
    p = p * 5.421010862427522e-20 if ki & 64 else p
    p = p * 2.938735877055719e-39 if ki & 128 else p
    p = p * 8.636168555094445e-78 if ki & 256 else p
    p = p * 7.458340731200207e-155 if ki & 512 else p
    return p if p >= 2.2250738585072014e-308 else 0.0


def acos_unit(x: float) -> float:
    """``arccos(x)`` in radians for ``-1 <= x <= 1`` (within 1.5 ulp of the exact value; fdlibm's rational
    approximation).

    ``|x| <= 1/2``: ``pi/2 - (x + x R(x^2))``; else ``2 (s + s R(z))``, ``z = (1 - |x|) / 2``, ``s = sqrt(z)``,
    taken from ``pi`` for ``x < 0``. Both branches are computed and one is selected.
    """
    ax = abs(x)
    big = ax > 0.5
    z = (1.0 - ax) * 0.5 if big else x * x
    p = 3.47933107596021167570e-05  # fdlibm's pS5 ... pS0 and qS4 ... qS1
    p = p * z + 7.91534994289814532176e-04
    p = p * z - 4.00555345006794114027e-02
    p = p * z + 2.01212532134862925881e-01
    p = p * z - 3.25565818622400915405e-01
    p = p * z + 1.66666666666666657415e-01
    p = p * z
    q = 7.70381505559019352791e-02
    q = q * z - 6.88283971605453293030e-01
    q = q * z + 2.02094576023350569471e00
    q = q * z - 2.40339491173441421878e00
    q = q * z + 1.0
    r = p / q
    s = np.sqrt(z)
    far = 2.0 * (s + s * r)  # arccos(|x|) for |x| > 1/2
    far = np.pi - far if x < 0.0 else far
    near = 1.57079632679489655800e00 - (x - (6.12323399573676603587e-17 - x * r))
    return far if big else near


__all__ = ["acos_unit", "exp_neg", "exp_nonpositive"]
