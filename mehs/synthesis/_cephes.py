"""Float32 ``logf`` / ``expf`` (Cephes) on scalars, in a form LLVM vectorises.

pip's llvmlite has no SVML, so ``math.log`` in a compiled loop is a libm call per
sample and the loop stays scalar. These are the Cephes polynomials (≤ 2 ulp) with
``frexp`` / ``ldexp`` done on the float's bits through LLVM ``bitcast``
(:func:`f32_bits`, :func:`f32_from_bits`): no call, no memory, so a loop that uses
them vectorises like plain arithmetic. The stage kernels' row forms
(:func:`mehs.synthesis._merge_rows._exp_row`, ``_log_accumulate_row``) are loops over
them, so the one-pass and the stage kernels take the same ``ln`` and ``exp``.

Both are compiled with ``fastmath={"contract"}`` and nothing else: each ``c·v + d`` of
the polynomials may become one fused multiply-add (one rounding instead of two, so as
accurate or more; the ≤ 2 ulp bound is tested). They are not inlined at numba's level,
where the caller's flags would apply; LLVM inlines them and keeps their instructions'
flags, so the kernels' own arithmetic stays uncontracted. With the polynomials as FMAs
the Debevec merge (three ``ln`` and one ``exp`` per sample) takes 17 % less time
(issue 16). On a CPU without FMA the results differ in the last bit, as libm's do.

References
----------
- Moshier, S. L. (1992). Cephes Mathematical Library, ``expf.c`` / ``logf.c``.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from mehs.synthesis._numba_cache import drop_stale_kernel_caches

# the bottom of the kernel modules' imports: runs before any of their cached code loads
drop_stale_kernel_caches()

_LOG2E = np.float32(1.44269504088896341)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)


@intrinsic
def f32_bits(typingctx, x):
    """The int32 whose bits are the float32 ``x`` (C's ``memcpy`` type pun)."""
    if x != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def f32_from_bits(typingctx, b):
    """The float32 whose bits are the low 32 bits of the integer ``b``.

    (numba widens int32 arithmetic to int64, so any integer is taken and truncated.)
    """
    if not isinstance(b, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        v = args[0]
        if b.bitwidth > 32:
            v = builder.trunc(v, ir.IntType(32))
        elif b.bitwidth < 32:
            v = builder.sext(v, ir.IntType(32)) if b.signed else builder.zext(v, ir.IntType(32))
        return builder.bitcast(v, ir.FloatType())

    return types.float32(b), codegen


@njit(cache=True, error_model="numpy", fastmath={"contract"})
def logf(x):
    """``ln x`` for a positive, finite, normal float32 ``x`` (Cephes ``logf``)."""
    f1 = np.float32(1.0)
    b = f32_bits(x)
    e = np.float32((b >> np.int32(23)) - np.int32(126))
    m = f32_from_bits((b & np.int32(0x007FFFFF)) | np.int32(0x3F000000))
    small = m < np.float32(0.707106781186547524)
    e = e - (f1 if small else np.float32(0.0))
    v = (m + m - f1) if small else (m - f1)
    z = v * v
    y = ((((((((np.float32(7.0376836292e-2) * v - np.float32(1.1514610310e-1)) * v
               + np.float32(1.1676998740e-1)) * v - np.float32(1.2420140846e-1)) * v
             + np.float32(1.4249322787e-1)) * v - np.float32(1.6668057665e-1)) * v
           + np.float32(2.0000714765e-1)) * v - np.float32(2.4999993993e-1)) * v
         + np.float32(3.3333331174e-1)) * v * z
    y += e * _LN2_LO
    y += np.float32(-0.5) * z
    return v + y + e * _LN2_HI


@njit(cache=True, error_model="numpy", fastmath={"contract"})
def expf(x):
    """``exp x`` in float32 (Cephes ``expf``): 0 below ≈ −87.3, inf above ≈ 88.7, NaN kept."""
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    k = np.floor(x * _LOG2E + np.float32(0.5))
    k = min(max(k, np.float32(-127.0)), np.float32(128.0))
    r = (x - k * _LN2_HI) - k * _LN2_LO
    z = r * r
    p = ((((np.float32(1.9875691500e-4) * r + np.float32(1.3981999507e-3)) * r
           + np.float32(8.3334519073e-3)) * r + np.float32(4.1665795894e-2)) * r
         + np.float32(1.6666665459e-1)) * r + np.float32(5.0000001201e-1)
    # k = -127 → exponent bits 0 → 0.0 (underflow); k = 128 → inf
    scale = f32_from_bits((np.int32(k) + np.int32(127)) << np.int32(23))
    o = max((p * z + r + f1) * scale, f0)
    return o if x == x else x
