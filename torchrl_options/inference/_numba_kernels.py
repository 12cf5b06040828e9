"""The Numba kernels of :mod:`._numba_fb` (imported only when Numba is installed).

Everything is float64 inside, whatever the inputs' dtype. ``fastmath`` allows reassociation and contraction (so
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
