"""Data-parallel DDO: two gloo processes, each streaming its own shard of a demonstration buffer on disk, end with
the parameters one process reaches on all the trajectories (same data, same seed), to float rounding; the processes
agree with each other bit for bit, minibatches included."""
import json

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from torchrl_options import discover_options
from torchrl_options.data import demonstration_buffer, open_demonstrations, write_demonstrations
from torchrl_options.discovery.distributed import DataParallel, SingleProcess
from torchrl_options.testing import planted_corridor_demonstrations

WORLD = 2
RUNS = {
    # the defaults' machinery: segment starts chosen by likelihood, 5 G-steps per E-step, the stopping rule
    "full": dict(num_iterations=16, restarts=2, restart_iterations=4, tol=1e-4, patience=5),
    # full batch in E-step chunks of 2 trajectories per process (m_steps=1)
    "chunks": dict(num_iterations=10, m_steps=1, chunk_trajectories=2, restarts=1, init="random", tol=None),
    # minibatches of 4 trajectories (2 per process) and an evaluation set of 6
    "minibatch": dict(num_iterations=10, batch_size=4, eval_trajectories=6, restarts=1, init="random", tol=None),
}
COMMON = dict(seed=0, progress=False, return_info=True)


def _result(result):
    return {
        "params": {k: v.tolist() for k, v in result.options.state_dict().items()},
        "lls": [h["log_likelihood_per_step"] for h in result.history],
        "restarts": result.restart_log_likelihoods,
    }


def _worker(rank: int, init_file: str, path: str, out: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    try:
        buffer = open_demonstrations(path)  # every process opens the same files and reads its own shard
        results = {name: _result(discover_options(buffer, 2, distributed=True, **kw, **COMMON)) for name, kw in RUNS.items()}
        # refused on every process alike, before any training collective: another seed, another buffer
        refusals = {}
        quick = dict(num_iterations=2, restarts=1, init="random", progress=False)
        for case, call in (
            ("seed", lambda: discover_options(buffer, 2, distributed=True, seed=rank, **quick)),
            ("buffer", lambda: discover_options(open_demonstrations(f"{path}{'-short' if rank else ''}"), 2,
                                                distributed=True, seed=0, **quick)),
        ):  # fmt: skip
            try:
                call()
                refusals[case] = None
            except ValueError as err:
                refusals[case] = str(err)
        results["refusals"] = refusals
        with open(f"{out}/{rank}.json", "w") as f:
            json.dump(results, f)
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ddp")
    data = planted_corridor_demonstrations(8, 30, seed=0)
    write_demonstrations(demonstration_buffer(1000, path=tmp / "demos"), data)
    write_demonstrations(demonstration_buffer(1000, path=tmp / "demos-short"), data[:6])
    mp.spawn(_worker, args=(str(tmp / "init"), str(tmp / "demos"), str(tmp)), nprocs=WORLD, join=True)
    ranks = [json.loads((tmp / f"{r}.json").read_text()) for r in range(WORLD)]
    single = {name: _result(discover_options(open_demonstrations(tmp / "demos"), 2, **kw, **COMMON))
              for name, kw in RUNS.items()}  # fmt: skip
    return ranks, single


@pytest.mark.parametrize("name", list(RUNS))
def test_the_processes_agree_bit_for_bit(runs, name):
    ranks, _ = runs
    assert ranks[0][name] == ranks[1][name]


def test_processes_that_differ_are_refused_on_every_process(runs):
    ranks, _ = runs
    for rank, result in enumerate(ranks):
        seed, buffer = result["refusals"]["seed"], result["refusals"]["buffer"]
        assert seed is not None and buffer is not None, rank
        assert "the 2 processes must stream the same replay buffer with the same settings" in seed
        assert "seed (here %d, from 0 to 1 over the processes)" % rank in seed
        expected = 6 if rank else 8
        assert f"trajectories in the buffer (here {expected}, from 6 to 8 over the processes)" in buffer
        assert f"steps in the buffer (here {expected * 30}, from 180 to 240" in buffer


@pytest.mark.parametrize("name", ["full", "chunks"])
def test_two_processes_give_the_parameters_of_one(runs, name):
    ranks, single = runs
    two, one = ranks[0][name], single[name]
    assert len(two["lls"]) == len(one["lls"])
    assert two["restarts"] == pytest.approx(one["restarts"], abs=1e-5)
    assert two["lls"] == pytest.approx(one["lls"], abs=1e-5)
    for key, value in one["params"].items():
        assert torch.allclose(torch.tensor(two["params"][key]), torch.tensor(value), atol=1e-4, rtol=1e-4), key


def test_distributed_minibatches_train(runs):
    ranks, _ = runs
    lls = ranks[0]["minibatch"]["lls"]
    assert len(lls) == 10 and lls[-1] > lls[0]


def test_the_single_process_group_is_the_identity():
    group = SingleProcess()
    p = torch.nn.Parameter(torch.zeros(3))
    p.grad = torch.tensor([2.0, 4.0, 6.0])
    stats = group.reduce_gradients([p], torch.tensor([2.0, 7.0]))
    assert stats.tolist() == [2.0, 7.0] and p.grad.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="init_process_group"):
        DataParallel()
