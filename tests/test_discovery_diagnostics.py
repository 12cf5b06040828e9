"""discovery/diagnostics.py: unused and duplicated options, restarts that disagree, warnings of discover_options."""
import logging
import math

import pytest
import torch

from torchrl_options import discover_options
from torchrl_options.discovery import option_diagnostics, options_in_use, restart_disagreement, UNUSED_SHARE
from torchrl_options.testing import planted_corridor_demonstrations


def _log_probs(pi, term, B=3, T=6):
    K = len(pi)
    log_pi = torch.tensor(pi).log().expand(B, T, K).clone()
    log_term = torch.tensor(term).log().expand(B, T, K).clone()
    return dict(
        log_pi=log_pi, log_term=log_term, log_cont=torch.log1p(-log_term.exp()),
        log_eta=torch.full((B, T, K), -math.log(K)), mask=torch.ones(B, T, dtype=torch.bool),
    )  # fmt: skip


def test_usage_sums_to_one_and_follows_the_posterior():
    d = option_diagnostics(_log_probs([0.5, 0.5, 0.5], [0.3, 0.3, 0.3]))
    assert sum(d.usage) == pytest.approx(1.0) and d.usage == pytest.approx([1 / 3] * 3, abs=1e-6)
    d = option_diagnostics(_log_probs([0.9, 0.1], [0.3, 0.3]))  # option 1 explains every step 9 times worse
    assert d.usage[0] > 0.95 and d.unused == [1] and d.duplicates == []
    d = option_diagnostics(_log_probs([0.9, 0.5], [0.3, 0.3]))
    assert 0.5 < d.usage[0] < 0.95 and d.unused == [] and d.duplicates == []


def test_an_option_that_explains_nothing_is_reported_unused():
    d = option_diagnostics(_log_probs([0.9, 0.9, 1e-6], [0.2, 0.2, 0.2]))
    assert d.unused == [2]
    assert d.duplicates == [(0, 1)]
    assert any("less than" in w for w in d.warnings) and any("duplicates" in w for w in d.warnings)


def test_options_in_use_is_the_complement_of_unused():
    for pi in ([0.9, 0.1], [0.9, 0.9, 1e-6], [0.5, 0.5, 0.5], [0.9, 0.5]):
        d = option_diagnostics(_log_probs(pi, [0.3] * len(pi)))
        assert options_in_use(d.usage) == len(pi) - len(d.unused)
    # the threshold is UNUSED_SHARE / K, inclusive
    assert options_in_use([1 - UNUSED_SHARE / 2, UNUSED_SHARE / 2]) == 2
    assert options_in_use([1 - UNUSED_SHARE / 4, UNUSED_SHARE / 4]) == 1


def test_options_differing_only_in_termination_are_not_duplicates():
    d = option_diagnostics(_log_probs([0.6, 0.6], [0.05, 0.9]))
    assert d.duplicates == []


def test_padding_is_ignored():
    lp = _log_probs([0.9, 0.1], [0.3, 0.3])
    lp["mask"][:, 3:] = False
    lp["log_pi"][:, 3:] = float("nan")  # whatever padding holds
    d = option_diagnostics(lp)
    assert all(math.isfinite(u) for u in d.usage)


def test_restart_disagreement():
    assert restart_disagreement([]) is None and restart_disagreement([-1.0]) is None
    assert restart_disagreement([-1.0, -1.001, -1.5, -1.6]) is None
    message = restart_disagreement([-1.0, -1.2, -1.3, -1.4])
    assert message is not None and "1 of 4 starts" in message and "restarts" in message


def test_discover_options_reports_and_warns_about_duplicated_options(caplog):
    """Two options with the same parameters, not trained (learning rate 0): reported as duplicates and warned of."""
    from torchrl_options import OptionsMLP

    data = planted_corridor_demonstrations(8, 30, seed=0)
    torch.manual_seed(0)  # not the global RNG state earlier tests leave: an unseeded third option may act alike too
    options = OptionsMLP(2, 2, 3, num_cells=4)
    with torch.no_grad():
        for p in options.parameters():  # the K networks' parameters are stacked along the first dimension
            p[1] = p[0]
            p[2] = -p[0]  # option 2 prefers the other action and terminates where 0 continues: not a duplicate
    frozen = lambda params, lr: torch.optim.SGD(params, lr=0.0)  # noqa: E731
    with caplog.at_level(logging.WARNING, logger="torchrl_options.discovery.stages"):
        result = discover_options(data, 3, options=options, optimizer=frozen, num_iterations=2, progress=False,
                                  return_info=True)  # fmt: skip
    assert result.duplicate_options == [(0, 1)]
    assert len(result.option_usage) == 3 and sum(result.option_usage) == pytest.approx(1.0, abs=1e-4)
    assert any("duplicates" in w for w in result.warnings)
    assert any("duplicates" in r.getMessage() for r in caplog.records)


def test_default_restarts_only_with_fresh_modules():
    data = planted_corridor_demonstrations(8, 30, seed=1)
    result = discover_options(data, 2, num_iterations=160, restart_iterations=10, seed=0, progress=False,
                              return_info=True)  # fmt: skip
    from torchrl_options.discovery import AUTO_RESTARTS, DEFAULT_RESTARTS

    assert len(result.restart_log_likelihoods) == AUTO_RESTARTS  # init="auto", the default
    random = discover_options(data, 2, init="random", num_iterations=160, restart_iterations=10, seed=0,
                              progress=False, return_info=True)  # fmt: skip
    assert len(random.restart_log_likelihoods) == DEFAULT_RESTARTS
    short = discover_options(data, 2, num_iterations=20, seed=0, progress=False, return_info=True)
    assert short.restart_log_likelihoods == []  # too few iterations for the starts of restart_iterations
    from torchrl_options import OptionsMLP

    own = discover_options(data, 2, options=OptionsMLP(2, 2, 2), num_iterations=160, restart_iterations=10,
                           progress=False, return_info=True)  # fmt: skip
    assert own.restart_log_likelihoods == []  # the user's module is trained once, no error
