"""Discovery on CUDA (``-m gpu``, skipped without a GPU; benchmarks/gpu_check.sh runs them on a lent machine): the
device run is the CPU run to float rounding, in memory and streamed, and a full-batch iteration synchronises the
host at most :data:`MAX_SYNCS` times."""
import warnings

import pytest
import torch

from torchrl_options import DDOLoss, discover_options
from torchrl_options.data import demonstration_buffer, write_demonstrations
from torchrl_options.discovery import fit_ddo, TabulatedDDO
from torchrl_options.modules import OptionsMLP
from torchrl_options.testing import planted_corridor_demonstrations

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

# per full-batch iteration with m_steps G-steps: the E-step's two checks in forward_backward (padding, a zero
# likelihood), its NaN check of the networks' outputs, the first G-step's check that the parameters are the
# E-step's, and the record read once (which the stopping rule needs)
MAX_SYNCS = 5


def _parameters(module):
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}


@pytest.mark.parametrize("streamed", [False, True])
def test_the_cuda_run_is_the_cpu_run_to_float_rounding(streamed):
    data = planted_corridor_demonstrations(16, 60, seed=0)
    kw = dict(num_iterations=30, restarts=1, init="random", tol=None, seed=0, progress=False, return_info=True)
    if streamed:
        buffer = demonstration_buffer(10_000)
        write_demonstrations(buffer, data)
        data = buffer
    cpu = discover_options(data, 3, device="cpu", **kw)
    gpu = discover_options(data, 3, device="cuda", **kw)
    assert next(gpu.options.parameters()).device.type == "cuda"
    for a, b in zip(cpu.history, gpu.history):
        assert b["log_likelihood_per_step"] == pytest.approx(a["log_likelihood_per_step"], abs=1e-4)
    for key, value in _parameters(cpu.options).items():
        assert torch.allclose(_parameters(gpu.options)[key], value, atol=1e-3, rtol=1e-3), key


def _synchronisations(num_iterations: int) -> list[str]:
    data = planted_corridor_demonstrations(16, 60, seed=0).to("cuda")
    torch.manual_seed(0)
    loss = DDOLoss(OptionsMLP(2, 2, 3)).to("cuda")
    optimizer = torch.optim.Adam(loss.parameters(), lr=0.03, fused=True)
    table = TabulatedDDO(loss, data)
    fit_ddo(loss, optimizer, lambda it: table, 1, e_step=TabulatedDDO.e_step, m_steps=5, progress=False, log_every=0)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fit_ddo(loss, optimizer, lambda it: table, num_iterations, e_step=TabulatedDDO.e_step, m_steps=5, tol=1e-9,
                    patience=1000, progress=False, log_every=0)  # fmt: skip
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return [f"{w.filename}:{w.lineno}" for w in caught if "synchroniz" in str(w.message).lower()]


def test_a_full_batch_iteration_synchronises_the_host_at_most_max_syncs_times():
    two, six = _synchronisations(2), _synchronisations(6)
    per_iteration = (len(six) - len(two)) / 4
    assert per_iteration <= MAX_SYNCS, f"{per_iteration} synchronisations per iteration, from {sorted(set(six))}"
