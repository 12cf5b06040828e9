"""The Triton kernel of :mod:`._triton_fb`, in its own module so that importing it (and thus Triton, whose
interpreter mode is read when a kernel is defined) happens only when the Triton backend is first used."""
import triton
import triton.language as tl

@triton.jit
def _lse(x, axis: tl.constexpr):
    # logsumexp over the options (kept as a [BLOCK_B, 1] column); -inf when every entry is -inf.
    m = tl.max(x, axis=axis)
    m = tl.where(m == float("-inf"), 0.0, m)
    return tl.log(tl.sum(tl.exp(x - m[:, None]), axis=axis)) + m

@triton.jit
def _logaddexp(x, y):
    m = tl.maximum(x, y)
    m = tl.where(m == float("-inf"), 0.0, m)
    return m + tl.log(tl.exp(x - m) + tl.exp(y - m))

@triton.jit
def _fb_kernel(
    pi_ptr, term_ptr, cont_ptr, eta_ptr, end_ptr, last_ptr,
    alpha_ptr, u_ptr, v_ptr, w_ptr, ll_ptr,
    B, T, K,
    BLOCK_B: tl.constexpr, KP: tl.constexpr,
):
    pid = tl.program_id(0)
    rows = pid * BLOCK_B + tl.arange(0, BLOCK_B)
    ks = tl.arange(0, KP)
    row_ok = rows < B
    k_ok = ks < K
    ok = row_ok[:, None] & k_ok[None, :]
    base = rows.to(tl.int64)[:, None] * T * K + ks[None, :]  # offsets of step 0
    last = tl.load(last_ptr + rows, mask=row_ok, other=0)
    end = tl.load(end_ptr + rows[:, None] * K + ks[None, :], mask=ok, other=float("-inf"))

    # ---- forward: alpha_t normalised over the options, log-likelihood from the normalisers
    eta = tl.load(eta_ptr + base, mask=ok, other=float("-inf"))
    z = _lse(eta, 1)
    a = eta - z[:, None]
    ll = z
    a_last = a
    for t in range(0, T):
        off = base + t * K
        tl.store(alpha_ptr + off, a, mask=ok)
        a_last = tl.where((last == t)[:, None], a, a_last)
        if t + 1 < T:
            pi = tl.load(pi_ptr + off, mask=ok, other=float("-inf"))
            sw = pi + tl.load(term_ptr + off, mask=ok, other=0.0)
            st = pi + tl.load(cont_ptr + off, mask=ok, other=0.0)
            eta_n = tl.load(eta_ptr + off + K, mask=ok, other=float("-inf"))
            s = _lse(a + sw, 1)
            n = _logaddexp(s[:, None] + eta_n, a + st)
            z = _lse(n, 1)
            a = n - z[:, None]
            ll += tl.where(t < last, z, 0.0)
    ll += _lse(a_last + end, 1)
    tl.store(ll_ptr + rows, ll, mask=row_ok)

    # ---- backward: beta_t in registers; u_t, w_t and v_{t+1} written at step t
    b = end - _lse(end, 1)[:, None]
    eta_n = tl.zeros((BLOCK_B, KP), dtype=a.dtype)
    for i in range(0, T):
        t = T - 1 - i
        off = base + t * K
        pi = tl.load(pi_ptr + off, mask=ok, other=float("-inf"))
        sw = pi + tl.load(term_ptr + off, mask=ok, other=0.0)
        st = pi + tl.load(cont_ptr + off, mask=ok, other=0.0)
        eta = tl.load(eta_ptr + off, mask=ok, other=float("-inf"))
        a = tl.load(alpha_ptr + off, mask=ok, other=float("-inf"))
        before = (t < last)[:, None]
        # beta_t from beta_{t+1} (b) for t < last; the end factor at t = last; padding keeps anything finite.
        g = _lse(eta_n + b, 1)
        rec = _logaddexp(sw + g[:, None], st + b)
        nb = tl.where(before, rec, end)
        nb = nb - _lse(nb, 1)[:, None]
        # transition t -> t + 1 (only for t < last): start a new option at t + 1 (v) or keep h (w).
        s = _lse(a + sw, 1)
        log_sw = s[:, None] + eta_n + b
        log_st = a + st + b
        norm = _logaddexp(_lse(log_sw, 1), _lse(log_st, 1))
        v_next = tl.where(before, tl.exp(log_sw - norm[:, None]), 0.0)
        w_t = tl.where(before, tl.exp(log_st - norm[:, None]), 0.0)
        tl.store(w_ptr + off, w_t, mask=ok)
        if t + 1 < T:
            tl.store(v_ptr + off + K, v_next, mask=ok)
        x = a + nb
        x = x - _lse(x, 1)[:, None]
        u_t = tl.where((t <= last)[:, None], tl.exp(x), 0.0)
        tl.store(u_ptr + off, u_t, mask=ok)
        if t == 0:
            tl.store(v_ptr + off, u_t, mask=ok)
        b = nb
        eta_n = eta


@triton.jit
def _grad_kernel(
    u_ptr, v_ptr, w_ptr, tw_ptr, g_ptr,
    gpi_ptr, gterm_ptr, gcont_ptr, geta_ptr,
    N, TK, K,
    BLOCK: tl.constexpr,
):
    # The Expectation-Gradient in one pass: g*u, g*(u - w) where log_term counts, g*w, g*v (g = dL/dlog P per row).
    offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    ok = offs < N
    u = tl.load(u_ptr + offs, mask=ok, other=0.0)
    v = tl.load(v_ptr + offs, mask=ok, other=0.0)
    w = tl.load(w_ptr + offs, mask=ok, other=0.0)
    g = tl.load(g_ptr + offs // TK, mask=ok, other=0.0)
    tw = tl.load(tw_ptr + offs // K, mask=ok, other=0)
    tl.store(gpi_ptr + offs, g * u, mask=ok)
    tl.store(gterm_ptr + offs, tl.where(tw != 0, u - w, 0.0) * g, mask=ok)
    tl.store(gcont_ptr + offs, g * w, mask=ok)
    tl.store(geta_ptr + offs, g * v, mask=ok)
