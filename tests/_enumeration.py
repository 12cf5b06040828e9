"""Brute force over the options' latent chain, for tests of exact inference."""
import itertools


def latent_sequences(log_pi, log_term, log_cont, log_eta, L, terminal):
    """Yields ``(log P(zeta, xi), options, switches)`` for every latent sequence of a length-``L`` trajectory.

    ``b_0 = 1``; a new option may be the same one; ``terminal`` multiplies ``psi_h(s_T)``.
    """
    K = log_pi.shape[-1]
    for hs in itertools.product(range(K), repeat=L):
        for bs in itertools.product((0, 1), repeat=L - 1):
            b = (1,) + bs
            if any(b[t] == 0 and hs[t] != hs[t - 1] for t in range(1, L)):
                continue
            lp = log_eta[0, hs[0]] + log_pi[0, hs[0]]
            for t in range(1, L):
                step = log_term[t - 1, hs[t - 1]] + log_eta[t, hs[t]] if b[t] else log_cont[t - 1, hs[t - 1]]
                lp = lp + step + log_pi[t, hs[t]]
            if terminal:
                lp = lp + log_term[L - 1, hs[L - 1]]
            yield lp, hs, b
