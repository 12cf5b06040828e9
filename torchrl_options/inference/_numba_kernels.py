"""The Numba kernels of :mod:`._numba_fb` (imported only when Numba is installed).

:func:`fb32_rows` is the float32 kernel (float32 inputs, float32 arithmetic, explicit 8-lane vectors of
:mod:`._simd`); :func:`fb_rows` the float64 one, which also takes the rows the float32 kernel cannot certify.
In :func:`fb_rows` everything is float64 inside, whatever the inputs' dtype. ``fastmath`` allows reassociation and contraction (so
the loops over K vectorise) and assumes no NaN (the inputs are validated, padding is zeroed), but not ``ninf``:
``-inf`` log-probabilities must stay exact zeros; and not ``arcp``: ``u`` is a true quotient, so that it is
exactly 1 where a single option is possible.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from torchrl_options.inference._simd import (  # noqa: F401 (EXP_CONSTANTS: the kernels' callers pass it)
    EXP_CONSTANTS,
    exp_constants,
    nan_or_posinf,
    vadd,
    vdiv,
    vexp,
    vfirst,
    vfma,
    vhmax,
    vhmax8,
    vhmin,
    vload,
    vload_n,
    vmax,
    vmin,
    vmul,
    vsplat,
    vstore,
    vstore_n,
    vsub,
    vsum,
    vsum2,
    vsumv,
)

_FASTMATH = {"nnan", "contract", "reassoc", "nsz"}

# exp(x) for x <= 0: x = k ln2 + r, |r| <= ln2 / 2 (Cody-Waite, fdlibm's split of ln2), exp(r) by its Taylor
# series to degree 13 (truncation below 1e-17 relative), 2^k from the exponent bits. Below -708 (where 2^k would
# leave the normal range) the result is 0; the kernel flags a row whose finite log-factor goes there.
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_EXP_MIN = -708.0


def _noalias_pipeline():
    """A Numba compiler pipeline that marks the array arguments ``noalias`` (as Numba does for its parallel
    loops): the compiler then needs no run-time overlap checks between them before vectorising a loop. Only for
    kernels whose written arrays are fresh outputs, never another argument's memory (the inputs may alias each
    other: they are only read). ``None`` where this Numba does not offer it (then the kernels compile without it).
    """
    try:
        from numba.core.compiler import CompilerBase, DefaultPassBuilder
    except ImportError:  # pragma: no cover - another Numba layout
        return None

    class NoAliasCompiler(CompilerBase):
        def define_pipelines(self):
            try:
                self.state.flags.noalias = True
            except (AttributeError, TypeError, ValueError):  # pragma: no cover - a Numba without the flag
                pass
            return [DefaultPassBuilder.define_nopython_pipeline(self.state)]

    return NoAliasCompiler


_NOALIAS_PIPELINE = _noalias_pipeline()


def _jit(noalias=False, **kwargs):
    """``numba.njit`` with the on-disk cache where Numba finds a writable place for it, in memory otherwise;
    ``noalias``: compile with :func:`_noalias_pipeline` where available."""

    # error_model="numpy": a division by zero gives inf (a row of zero likelihood is flagged, not raised).
    kwargs.setdefault("error_model", "numpy")
    if noalias and _NOALIAS_PIPELINE is not None:
        kwargs["pipeline_class"] = _NOALIAS_PIPELINE

    def wrap(fn):
        try:
            return numba.njit(cache=True, **kwargs)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available": nowhere writable
            return numba.njit(cache=False, **kwargs)(fn)

    return wrap


@intrinsic
def _f64_from_bits(typingctx, x):
    """Reinterprets the bits of an int64 as a float64 (vectorisable, unlike ``math.ldexp``)."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.int64), codegen


@_jit(inline="always", fastmath=_FASTMATH)
def _exp_nonpos(x):
    """exp(x) for x <= 0 (to about 2 ulp); 0 for x < -708, -inf included."""
    xc = max(x, _EXP_MIN)
    k = math.floor(xc * _LOG2E + 0.5)
    r = (xc - k * _LN2_HI) - k * _LN2_LO
    p = 1.0 / 6227020800.0
    p = p * r + 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    scale = _f64_from_bits((np.int64(k) + 1023) << 52)
    return p * scale if x >= _EXP_MIN else 0.0


@_jit(inline="always", fastmath=_FASTMATH)
def _factor(x):
    """``(exp(x), bad)`` for a shifted log-factor ``x <= 0``: ``bad`` when x is finite but exp(x) flushed to 0."""
    f = _exp_nonpos(x)
    return f, (f == 0.0) & (x > -np.inf)


@_jit(noalias=True, nogil=True, fastmath=_FASTMATH)
def _flat_factors(lp, lt, lc, le, sd, se, D, C, E):
    """The factors of a row's transitions in one flat loop over its ``(L - 1) * K`` entries (long, so the compiler
    vectorises it; a loop over the K options of one step is too short for that): ``D = exp(lp + lc + sd)``,
    ``C = exp(lp + lt + (sd - se))``, ``E = exp(le + se)``, with the shifts of each entry's step ``sd = -m_t`` and
    ``se = -max_h log_eta_{t+1}(h)``; ``le`` is the row's ``log_eta`` from step 1 on. Returns whether a finite
    log-factor flushed to 0 (see :func:`_factor`)."""
    bad = False
    for i in range(D.shape[0]):
        p = np.float64(lp[i])
        d, bd = _factor(p + np.float64(lc[i]) + sd[i])
        c, bc = _factor(p + np.float64(lt[i]) + (sd[i] - se[i]))
        e, be = _factor(np.float64(le[i]) + se[i])
        D[i] = d
        C[i] = c
        E[i] = e
        bad |= bd | bc | be
    return bad


@_jit(noalias=True, nogil=True, fastmath=_FASTMATH)
def fb_rows(lp, lt, lc, le, lengths, terminal, ll_out, u, v, w, bad, floor, zfloor, sfloor, b0, b1):
    """Forward-backward of rows ``b0 .. b1 - 1`` (see :mod:`._numba_fb`): writes ``ll_out`` [B] (float64), ``u``,
    ``v``, ``w`` (zeros on padding) and ``bad`` [B] (the caller passes False; a flagged row's u, v, w are partial).

    Invariants checked on the way (else the row is flagged): a factor is 0 only where its log-probability is
    -inf; every entry of a normalised message that is mathematically non-zero (tracked from the -inf pattern) is
    at least ``floor``; each step's normaliser is at least ``zfloor`` and ``sum_h alpha_t(h) beta_t(h)`` at least
    ``sfloor``. Then what float64 drops (products below 1e-308) is negligible against every kept quantity, and
    every non-zero output carries float64's relative precision."""
    T, K = lp.shape[1], lp.shape[2]
    for b in range(b0, b1):
        L = lengths[b]
        D = np.empty((L, K))  # stay factors of transition t (step t -> t + 1)
        C = np.empty((L, K))  # terminate factors
        E = np.empty((L, K))  # start factors
        A = np.empty((L, K))  # normalised forward messages
        shift = np.empty(L)  # the log-scale taken out of transition t's factors
        sw = np.empty(L)  # switching mass of transition t
        zs = np.empty(L)  # normaliser of transition t
        n = np.empty(K)
        sup = np.empty(K, dtype=np.bool_)  # the entries of the current message that are mathematically non-zero
        flag = False

        # --- 1. factors, all transitions (no dependency between steps): each step's shifts, spread over its K
        # entries, then the exponentials in one flat loop over the row
        N = (L - 1) * K
        sd = np.empty(N)
        se = np.empty(N)
        for t in range(L - 1):
            me = -np.inf
            for h in range(K):
                me = max(me, np.float64(le[b, t + 1, h]))
            if me == -np.inf:
                me = 0.0
            md = -np.inf
            mc = -np.inf
            for h in range(K):
                p = np.float64(lp[b, t, h])
                md = max(md, p + np.float64(lc[b, t, h]))
                mc = max(mc, p + np.float64(lt[b, t, h]))
            m = max(md, mc + me)  # = max_h max(p + lc, p + lt + me): rounding is monotonic
            if m == -np.inf:
                m = 0.0
            shift[t] = m
            for h in range(K):
                sd[t * K + h] = -m
                se[t * K + h] = -me
        flag |= _flat_factors(
            lp[b].reshape(T * K)[:N], lt[b].reshape(T * K)[:N], lc[b].reshape(T * K)[:N],
            le[b].reshape(T * K)[K:K + N], sd, se,
            D.reshape(L * K)[:N], C.reshape(L * K)[:N], E.reshape(L * K)[:N],
        )  # fmt: skip

        # --- 2. forward ---------------------------------------------------------------------------------------
        me = -np.inf
        for h in range(K):
            me = max(me, np.float64(le[b, 0, h]))
        if me == -np.inf:
            me = 0.0
        z = 0.0
        for h in range(K):
            e, be = _factor(np.float64(le[b, 0, h]) - me)
            flag |= be
            n[h] = e
            sup[h] = e > 0.0
            z += e
        log_lik = me + math.log(z)
        rz = 1.0 / z
        for h in range(K):
            A[0, h] = n[h] * rz
        prod = 1.0  # product of the normalisers since the last log
        for t in range(L - 1):
            # z = sum_h (s E + a D) = s sum(E) + sum(a D): three independent sums, so that the step's
            # dependency chain (a_t -> a_{t+1}) holds one reduction, not two
            s = 0.0
            q = 0.0
            es = 0.0
            ssup = False
            for h in range(K):
                ah = A[t, h]
                s += ah * C[t, h]
                q += ah * D[t, h]
                es += E[t, h]
                ssup |= sup[h] & (C[t, h] > 0.0)
            z = s * es + q
            flag |= not (z >= zfloor)
            rz = 1.0 / z
            for h in range(K):
                a = (s * E[t, h] + A[t, h] * D[t, h]) * rz
                A[t + 1, h] = a
                sh = (ssup & (E[t, h] > 0.0)) | (sup[h] & (D[t, h] > 0.0))
                sup[h] = sh
                flag |= sh & (a < floor)
            sw[t] = s
            zs[t] = z
            log_lik += shift[t]
            prod *= z
            if prod < 1e-200:
                log_lik += math.log(prod)
                prod = 1.0
        log_lik += math.log(prod)

        # --- the end factor: pi at the last step (times psi there when the row is terminal) -------------------
        last = L - 1
        mf = -np.inf
        for h in range(K):
            x = np.float64(lp[b, last, h])
            if terminal[b]:
                x += np.float64(lt[b, last, h])
            mf = max(mf, x)
        if mf == -np.inf:
            mf = 0.0
        zf = 0.0
        za = 0.0
        for h in range(K):
            x = np.float64(lp[b, last, h])
            if terminal[b]:
                x += np.float64(lt[b, last, h])
            f, bf = _factor(x - mf)
            flag |= bf
            n[h] = f
            sup[h] = f > 0.0
            zf += f
            za += A[last, h] * f
        flag |= not (za >= zfloor)
        ll_out[b] = log_lik + mf + math.log(za)
        # padding, and w at the last valid step, are zeros
        for t in range(L, u.shape[1]):
            for h in range(K):
                u[b, t, h] = 0.0
                v[b, t, h] = 0.0
                w[b, t, h] = 0.0
        for h in range(K):
            w[b, last, h] = 0.0
        if flag:
            bad[b] = True
            continue

        # --- 3. backward, fused with the marginals ------------------------------------------------------------
        bv = np.empty(K)  # beta_{t+1}, normalised
        rz = 1.0 / zf
        S = 0.0
        for h in range(K):
            x = n[h] * rz
            bv[h] = x
            S += A[last, h] * x
        rS = 1.0 / S
        for t in range(L - 2, -1, -1):
            # marginals of transition t, from beta_{t+1} and S_{t+1} = sum a_{t+1} beta_{t+1}: with
            # n_{t+1} = s E + a_t D = z a_{t+1}, v_{t+1} = (s E / z) beta / S and w_t = (a_t D / z) beta / S.
            rz = 1.0 / zs[t]
            qs = sw[t] * rz
            g = 0.0
            r = 0.0
            cs = 0.0
            gsup = False
            for h in range(K):
                e = E[t, h]
                x = bv[h]
                u[b, t + 1, h] = (A[t + 1, h] * x) / S
                v[b, t + 1, h] = (qs * e) * x * rS
                w[b, t, h] = (A[t, h] * D[t, h] * rz) * x * rS
                g += e * x
                r += D[t, h] * x
                cs += C[t, h]
                gsup |= sup[h] & (e > 0.0)
            z = cs * g + r  # = sum_h (C g + D b), as in the forward pass
            flag |= not (z >= zfloor)
            rz = 1.0 / z
            S = 0.0
            for h in range(K):
                x = (C[t, h] * g + D[t, h] * bv[h]) * rz
                sh = (gsup & (C[t, h] > 0.0)) | (sup[h] & (D[t, h] > 0.0))
                sup[h] = sh
                flag |= sh & (x < floor)
                bv[h] = x
                S += A[t, h] * x
            flag |= not (S >= sfloor)
            rS = 1.0 / S
        for h in range(K):  # u_t is written with transition t's marginals, u_0 here
            u[b, 0, h] = (A[0, h] * bv[h]) / S
            v[b, 0, h] = u[b, 0, h]
        if flag:
            bad[b] = True


@_jit(noalias=True, nogil=True, fastmath=_FASTMATH)
def grad_rows(g, u, v, w, lengths, terminal, g_pi, g_term, g_cont, g_eta, b0, b1):
    """The Expectation-Gradient of rows ``b0 .. b1 - 1`` in one pass: ``g u``, ``g (u - w)``, ``g w`` and ``g v``,
    with ``g`` the row's ``grad_ll``, except ``g_term = g * 0`` at a non-terminal row's last valid step (log_term
    does not enter its likelihood there; after it, on padding, ``u = w = 0``, and at a terminal row's last step
    ``w = 0``, so ``g (u - w)`` is already what the likelihood's gradient is).

    Each row is a contiguous ``T * K`` block, so the loops run flat over it (long, vectorised)."""
    T, K = u.shape[1], u.shape[2]
    N = T * K
    for b in range(b0, b1):
        gb = g[b]
        ub = u[b].reshape(N)
        vb = v[b].reshape(N)
        wb = w[b].reshape(N)
        pb = g_pi[b].reshape(N)
        tb = g_term[b].reshape(N)
        cb = g_cont[b].reshape(N)
        eb = g_eta[b].reshape(N)
        for i in range(N):
            pb[i] = gb * ub[i]
        for i in range(N):
            tb[i] = gb * (ub[i] - wb[i])
        for i in range(N):
            cb[i] = gb * wb[i]
        for i in range(N):
            eb[i] = gb * vb[i]
        if not terminal[b]:
            last = lengths[b] - 1
            for h in range(K):
                g_term[b, last, h] = gb * 0.0


# ---------------------------------------------------------------------------------------------------------------
# The float32 kernel
# ---------------------------------------------------------------------------------------------------------------

_W = 8  # lanes of a vector of :mod:`._simd`
_Z32 = np.float32(0.0)
_ONE32 = np.float32(1.0)
_NINF32 = np.float32(-np.inf)
_INF32 = np.float32(np.inf)
_NO_SHIFT32 = np.float32(-3.4e38)  # the shift of a step whose every log pi is -inf


@_jit(inline="always")
def _ld(x, i, n):
    """``x[i:i + 8]``; when fewer than 8 options are left (``n < 8``) the missing lanes hold ``-inf``."""
    if n >= _W:
        return vload(x, i)
    return vload_n(x, i, n, _NINF32)


@_jit(inline="always")
def _st(x, i, v, n):
    """``x[i:i + min(n, 8)] = v``."""
    if n >= _W:
        vstore(x, i, v)
    else:
        vstore_n(x, i, v, n)


@_jit(inline="always")
def _start32(leb, K, NC, KP, X, padv, ec):
    """``alpha_0 = eta_0`` normalised, into the message slot of ``X``'s step 0. Returns its log-normaliser, the
    validity sum of the ``log_eta`` entries read and the smallest entry before normalisation (lane-wise)."""
    mx = vsplat(_NINF32)
    for c in range(NC):
        mx = vmax(mx, _ld(leb, c * _W, K - c * _W))
    me = vhmax(mx)
    if me == _NINF32:
        me = _Z32
    acc = vsplat(_Z32)
    chk = vsplat(_Z32)
    for c in range(NC):
        x = _ld(leb, c * _W, K - c * _W)
        chk = vadd(chk, x)
        e = vexp(vsub(x, vsplat(me)), ec)
        vstore(X, 3 * KP + c * _W, e)
        acc = vadd(acc, e)
    z = vsum(acc)
    rz = vsplat(_ONE32 / z)
    mn = vsplat(_INF32)
    for c in range(NC):
        i = 3 * KP + c * _W
        e = vload(X, i)
        mn = vmin(mn, vmax(e, vload(padv, c * _W)))
        vstore(X, i, vmul(e, rz))
    return np.float64(me) + math.log(np.float64(z)), chk, mn


@_jit(inline="always")
def _stepmax(lpb, o, K, NC):
    """The lane-wise maximum of the ``NC`` vectors of one step's ``log_pi`` (at element offset ``o``)."""
    mx = _ld(lpb, o, K)
    for c in range(1, NC):
        mx = vmax(mx, _ld(lpb, o + c * _W, K - c * _W))
    return mx


@_jit(inline="always")
def _shifts32(lpb, n, K, NC, SH):
    """``SH[t]``: the shift of step ``t < n``, its largest ``log pi``, eight steps at a time (:func:`vhmax8`), in
    a pass before the forward one (there the shift's horizontal maximum sat on every step's path to its
    exponentials: 9% of the kernel's time at K = 8). Returns their sum (float64). A step whose every ``log pi`` is
    ``-inf`` gets ``_NO_SHIFT32`` (its factors stay exact zeros, and the row, of zero likelihood, fails the
    certificate)."""
    lo = vsplat(_NO_SHIFT32)
    t = 0
    while t + _W <= n:
        o = t * K
        m = vhmax8(_stepmax(lpb, o, K, NC), _stepmax(lpb, o + K, K, NC), _stepmax(lpb, o + 2 * K, K, NC),
                   _stepmax(lpb, o + 3 * K, K, NC), _stepmax(lpb, o + 4 * K, K, NC), _stepmax(lpb, o + 5 * K, K, NC),
                   _stepmax(lpb, o + 6 * K, K, NC), _stepmax(lpb, o + 7 * K, K, NC))  # fmt: skip
        vstore(SH, t, vmax(m, lo))
        t += _W
    for t in range(t, n):
        SH[t] = max(vhmax(_stepmax(lpb, t * K, K, NC)), _NO_SHIFT32)
    tot = 0.0
    for t in range(n):
        tot += np.float64(SH[t])
    return tot


@_jit(inline="always")
def _step32_one(lpb, ltb, lcb, leb, t, K, X, RZ, QS, SH, a, chk, mn, fx, prod, llv, pad, ec):
    """Forward step ``t -> t + 1`` for K <= 8 (one vector per step), the message ``a`` kept in a register: the
    step's factors (stored in ``X`` for the backward pass) and the new normalised message."""
    j = t * 4 * _W
    o = t * K
    lpv = _ld(lpb, o, K)
    p = vsub(lpv, vsplat(SH[t]))  # the step's shift: its largest log pi
    x1 = vadd(p, _ld(lcb, o, K))
    x2 = vadd(p, _ld(ltb, o, K))
    y = _ld(leb, o + K, K)
    chk = vadd(chk, vadd(vadd(x1, x2), y))
    fx = vmax(fx, vmax(vmax(x1, x2), y))
    d = vexp(x1, ec)  # stay: pi (1 - psi)
    cc = vexp(x2, ec)  # terminate: pi psi
    e = vexp(y, ec)  # start: eta_{t+1}
    vstore(X, j, d)
    vstore(X, j + _W, cc)
    vstore(X, j + 2 * _W, e)
    ad = vmul(a, d)
    sv = vsumv(vmul(a, cc))
    zv = vfma(sv, vsumv(e), vsumv(ad))
    rzv = vdiv(vsplat(_ONE32), zv)
    n = vfma(sv, e, ad)
    a = vmul(n, rzv)
    rz = vfirst(rzv)
    RZ[t] = rz
    QS[t] = vfirst(sv) * rz
    prod *= np.float64(vfirst(zv))
    if prod < 1e-280:
        llv += math.log(prod)
        prod = 1.0
    mn = vmin(mn, vmax(n, pad))
    vstore(X, j + 7 * _W, a)
    return a, chk, mn, fx, prod, llv


@_jit(inline="always")
def _step32(lpb, ltb, lcb, leb, t, K, NC, KP, X, RZ, QS, SH, chk, mn, fx, prod, llv, padv, ec):
    """Forward step ``t -> t + 1``, any K (``NC`` vectors per step), the message in ``X``."""
    j = t * 4 * KP
    o = t * K
    mv = vsplat(SH[t])  # the step's shift: its largest log pi
    ea = vsplat(_Z32)
    sa = vsplat(_Z32)
    qa = vsplat(_Z32)
    for c in range(NC):
        n = K - c * _W
        k = j + c * _W
        p = vsub(_ld(lpb, o + c * _W, n), mv)
        x1 = vadd(p, _ld(lcb, o + c * _W, n))
        x2 = vadd(p, _ld(ltb, o + c * _W, n))
        y = _ld(leb, o + K + c * _W, n)
        chk = vadd(chk, vadd(vadd(x1, x2), y))
        fx = vmax(fx, vmax(vmax(x1, x2), y))
        d = vexp(x1, ec)
        cc = vexp(x2, ec)
        e = vexp(y, ec)
        vstore(X, k, d)
        vstore(X, k + KP, cc)
        vstore(X, k + 2 * KP, e)
        a = vload(X, k + 3 * KP)
        ea = vadd(ea, e)
        sa = vfma(a, cc, sa)
        qa = vfma(a, d, qa)
    s = vsum(sa)
    z = s * vsum(ea) + vsum(qa)
    rz = _ONE32 / z
    RZ[t] = rz
    QS[t] = s * rz
    prod *= np.float64(z)
    if prod < 1e-280:
        llv += math.log(prod)
        prod = 1.0
    sv = vsplat(s)
    rzv = vsplat(rz)
    for c in range(NC):
        k = j + c * _W
        n = vfma(sv, vload(X, k + 2 * KP), vmul(vload(X, k + 3 * KP), vload(X, k)))
        mn = vmin(mn, vmax(n, vload(padv, c * _W)))
        vstore(X, k + 7 * KP, vmul(n, rzv))
    return chk, mn, fx, prod, llv


@_jit(noalias=True, nogil=True, fastmath=_FASTMATH)
def _finish32(b, L, T, K, NC, KP, lpb, ltb, lcb, term, X, RZ, QS, chk, mn, fx, prod, llv, tiny,
              ub, vb, wb, gpb, gtb, gcb, geb, grads, bv, wn, padv, ll_out, status, ec):  # fmt: skip
    """Row ``b`` after its forward pass: the end factor, the backward pass fused with the marginals (and, with
    ``grads``, the four gradients for an upstream gradient of 1), zeros on padding, and the row's status."""
    S4 = 4 * KP
    zerov = vsplat(_Z32)
    last = L - 1
    o = last * K
    j = last * S4
    # the end factor: pi at the last step (times psi there if the row is terminal)
    mx = vsplat(_NINF32)
    for c in range(NC):
        n = K - c * _W
        p = _ld(lpb, o + c * _W, n)
        q = _ld(ltb, o + c * _W, n)
        chk = vadd(chk, vadd(vadd(p, q), _ld(lcb, o + c * _W, n)))
        if term:
            p = vadd(p, q)
        mx = vmax(mx, p)
    m = vhmax(mx)
    if m == _NINF32:
        m = _Z32
    qa = zerov
    for c in range(NC):
        n = K - c * _W
        p = _ld(lpb, o + c * _W, n)
        if term:
            p = vadd(p, _ld(ltb, o + c * _W, n))
        d = vexp(vsub(p, vsplat(m)), exp_constants(ec))
        vstore(X, j + c * _W, d)
        qa = vfma(vload(X, j + 3 * KP + c * _W), d, qa)
    z = vsum(qa)
    ll_out[b] = llv + np.float64(m) + math.log(prod * np.float64(z))
    if nan_or_posinf(vsum(chk)):  # a NaN or +inf among the entries read (-inf + inf is NaN too)
        status[b] |= 2
    for i in range(L * K, T * K):
        ub[i] = _Z32
        vb[i] = _Z32
        wb[i] = _Z32
    for i in range(last * K, L * K):
        wb[i] = _Z32
    if grads:
        for i in range(L * K, T * K):
            gpb[i] = _Z32
            gtb[i] = _Z32
            gcb[i] = _Z32
            geb[i] = _Z32
    # beta_{L-1} = f / z; every beta is scaled by its step's forward normaliser (so sum_h alpha_t beta_t = 1 in
    # exact arithmetic) and S_t = sum_h alpha_t beta_t, computed, normalises the marginals
    rz = vsplat(_ONE32 / z)
    acc = zerov
    bsv = zerov
    for c in range(NC):
        x = vmul(vload(X, j + c * _W), rz)
        vstore(bv, c * _W, x)
        vstore(wn, c * _W, zerov)
        acc = vfma(vload(X, j + 3 * KP + c * _W), x, acc)
        bsv = vadd(bsv, x)
    S = vsum(acc)
    bs = vsum(bsv)
    # the certificate's backward half: each new entry C g + D beta must be at least tiny * sum(beta) * (C + D)
    # (see fb32_rows), lane-wise minimum over the steps of the difference (for K <= 8 both sides scaled by the
    # step's 1 / z, which the factors then carry)
    mnb = vsplat(_INF32)
    if NC == 1:  # K <= 8: beta in a register
        x = vload(bv, 0)
        wprev = zerov
        for t in range(L - 2, -1, -1):
            j = t * S4
            o = t * K
            rS = _ONE32 / S
            e = vload(X, j + 2 * _W)
            d = vload(X, j)
            a0 = vload(X, j + 3 * _W)
            # transition t's marginals: u_{t+1} = alpha beta / S, v_{t+1} = (s E / z) beta / S,
            # w_t = (alpha_t D / z) beta / S
            uu = vdiv(vmul(vload(X, j + 7 * _W), x), vsplat(S))
            vv = vmul(vsplat(QS[t] * rS), vmul(e, x))
            ww = vmul(vmul(vmul(a0, d), vsplat(RZ[t] * rS)), x)
            _st(ub, o + K, uu, K)
            _st(vb, o + K, vv, K)
            _st(wb, o, ww, K)
            if grads:
                _st(gpb, o + K, uu, K)
                _st(geb, o + K, vv, K)
                _st(gcb, o, ww, K)
                _st(gtb, o + K, vsub(uu, wprev), K)
                wprev = ww
            gv = vsumv(vmul(e, x))
            rzt = vsplat(RZ[t])
            ccr = vmul(vload(X, j + _W), rzt)
            dr = vmul(d, rzt)
            x = vfma(ccr, gv, vmul(dr, x))
            mnb = vmin(mnb, vsub(x, vmul(vsplat(tiny * bs), vadd(ccr, dr))))
            S, bs = vsum2(vmul(a0, x), x)
        vstore(bv, 0, x)
        vstore(wn, 0, wprev)
    else:
        for t in range(L - 2, -1, -1):
            j = t * S4
            o = t * K
            rS = _ONE32 / S
            Sv = vsplat(S)
            qs = vsplat(QS[t] * rS)
            rzs = vsplat(RZ[t] * rS)
            ga = zerov
            for c in range(NC):
                n = K - c * _W
                k = j + c * _W
                x = vload(bv, c * _W)
                e = vload(X, k + 2 * KP)
                uu = vdiv(vmul(vload(X, k + 7 * KP), x), Sv)
                vv = vmul(qs, vmul(e, x))
                ww = vmul(vmul(vmul(vload(X, k + 3 * KP), vload(X, k)), rzs), x)
                _st(ub, o + K + c * _W, uu, n)
                _st(vb, o + K + c * _W, vv, n)
                _st(wb, o + c * _W, ww, n)
                if grads:
                    _st(gpb, o + K + c * _W, uu, n)
                    _st(geb, o + K + c * _W, vv, n)
                    _st(gcb, o + c * _W, ww, n)
                    _st(gtb, o + K + c * _W, vsub(uu, vload(wn, c * _W)), n)
                    vstore(wn, c * _W, ww)
                ga = vfma(e, x, ga)
            gv = vsplat(vsum(ga))
            rz = vsplat(RZ[t])
            thr = vsplat(tiny * bs)
            acc = zerov
            bsv = zerov
            for c in range(NC):
                k = j + c * _W
                cc = vload(X, k + KP)
                d = vload(X, k)
                nb = vfma(cc, gv, vmul(d, vload(bv, c * _W)))
                mnb = vmin(mnb, vsub(nb, vmul(thr, vadd(cc, d))))
                x = vmul(nb, rz)
                vstore(bv, c * _W, x)
                acc = vfma(vload(X, k + 3 * KP), x, acc)
                bsv = vadd(bsv, x)
            S = vsum(acc)
            bs = vsum(bsv)
    Sv = vsplat(S)
    for c in range(NC):
        n = K - c * _W
        uu = vdiv(vmul(vload(X, 3 * KP + c * _W), vload(bv, c * _W)), Sv)
        _st(ub, c * _W, uu, n)
        _st(vb, c * _W, uu, n)
        if grads:
            _st(gpb, c * _W, uu, n)
            _st(geb, c * _W, uu, n)
            _st(gtb, c * _W, vsub(uu, vload(wn, c * _W)), n)
    if grads:
        for i in range(last * K, L * K):
            gcb[i] = _Z32
            if not term:
                gtb[i] = _Z32
    if not (vhmin(mn) >= tiny and z >= tiny and vhmax(fx) <= _Z32 and vhmin(mnb) >= _Z32):
        status[b] |= 1


@_jit(noalias=True, nogil=True, fastmath=_FASTMATH)
def fb32_rows(lp, lt, lc, le, T, K, lengths, terminal, ll_out, u, v, w, gp, gt, gc, ge, grads, status, tiny,
              ec, b0, b1):  # fmt: skip
    """Forward-backward of rows ``b0 .. b1 - 1`` in float32 (see :mod:`._numba_fb`). Inputs and outputs are
    ``[B, T * K]`` float32 (C-contiguous); only each row's valid prefix of the inputs is read. Writes ``ll_out``
    [B] (float64), ``u``, ``v``, ``w`` and, with ``grads``, ``gp``, ``gt``, ``gc``, ``ge`` (the Expectation-Gradient
    for an upstream gradient of 1: ``u``, ``u - w`` where log_term enters the likelihood else 0, ``w``, ``v``),
    zeros on padding. ``status[b]`` (the caller passes 0): bit 0 set if the row could not be certified (the
    caller recomputes it), bit 1 if a valid entry read is NaN or +inf.

    Float32 drops products below 1.2e-38 (and exponentials of log-factors below -87, 1.6e-38); with every factor at
    most 1 (checked: log-factors after the shift at most 0) and the forward messages normalised, each dropped term
    is at most 1.6e-38 (times ``sum(beta)`` in the backward pass), so an entry made of ``K + 1`` terms loses at most
    ``(K + 1) 1.6e-38``. The certificate, with ``tiny = (K + 1) 1.6e-38 / 1e-8``: every forward entry before
    normalisation (``(C . alpha) E + D alpha``, and ``eta_0`` relative to its largest entry) is at least ``tiny``,
    so that it carries float32's relative precision (what it lost is below 1e-8 of it); every backward entry before
    scaling, ``(E . beta) C + D beta``, is at least ``tiny * sum(beta) * (C + D)``, so that what was lost from
    ``beta`` is below 1e-8 of each entry it enters (an entry of beta is small only through its own step's factors
    ``C + D``, i.e. its option's probability of the action; those entries carry absolute errors below
    ``1e-37 sum(beta)``, far below what float32 resolves in ``u``, ``v``, ``w``); and the last normaliser (the
    likelihood of the end) is at least ``tiny``. Exact zeros (``-inf`` log-probabilities) stay exact zeros.
    Rows that fail go to :func:`fb_rows`."""
    NC = (K + _W - 1) // _W
    KP = NC * _W
    X = np.zeros((T + 1) * 4 * KP, np.float32)  # per step t: D, C, E (transition t) and the message alpha_t
    RZ = np.empty(T, np.float32)  # 1 / z_t
    QS = np.empty(T, np.float32)  # s_t / z_t
    SH = np.empty(T, np.float32)  # the steps' shifts (their largest log pi)
    bv = np.zeros(KP, np.float32)
    wn = np.zeros(KP, np.float32)
    padv = np.zeros(KP, np.float32)  # +inf on the lanes beyond K (excluded from the minima), 0 elsewhere
    for h in range(K, KP):
        padv[h] = _INF32
    c = exp_constants(ec)
    for b in range(b0, b1):
        L = lengths[b]
        lpb, ltb, lcb, leb = lp[b], lt[b], lc[b], le[b]
        llv, chk, mn = _start32(leb, K, NC, KP, X, padv, c)
        fx = vsplat(_NINF32)
        prod = 1.0
        llv += _shifts32(lpb, L - 1, K, NC, SH)
        if NC == 1:
            pad0 = vload(padv, 0)
            a = vload(X, 3 * _W)
            for t in range(L - 1):
                a, chk, mn, fx, prod, llv = _step32_one(lpb, ltb, lcb, leb, t, K, X, RZ, QS, SH, a, chk, mn, fx, prod,
                                                        llv, pad0, c)  # fmt: skip
        else:
            for t in range(L - 1):
                chk, mn, fx, prod, llv = _step32(lpb, ltb, lcb, leb, t, K, NC, KP, X, RZ, QS, SH, chk, mn, fx, prod, llv,
                                                 padv, c)  # fmt: skip
        _finish32(b, L, T, K, NC, KP, lpb, ltb, lcb, terminal[b], X, RZ, QS, chk, mn, fx, prod, llv, tiny, u[b],
                  v[b], w[b], gp[b], gt[b], gc[b], ge[b], grads, bv, wn, padv, ll_out, status, ec)  # fmt: skip
