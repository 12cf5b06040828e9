"""Bad inputs of torchrl_options.discovery (issue 53) at the doors this issue owns: split-and-merge moves, the
label-free diagnostics, saving options and the tabulated E-step (discover_options itself and the initialisations
are issue 51's; their older cases are in tests/test_bad_inputs_io.py). One row per case, controls included."""
import math
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from _bad_inputs import check, ids, OK
from torchrl_options import DDOLoss, MetaControlMLP, OptionsMLP, save_options
from torchrl_options.discovery import (
    change_points,
    option_diagnostics,
    options_in_use,
    restart_disagreement,
    TabulatedDDO,
    unique_rows,
    UsageFloor,
    check_usage_floor,
)
from torchrl_options.discovery.split_merge import check_split_merge_options, copy_option, propose_pairs, split_merge

NAN = float("nan")
G = torch.Generator().manual_seed(0)


def log_probs(K=3, B=2, T=5, **change):
    log_pi = torch.log(torch.tensor([0.9, 0.9, 0.1][:K])).expand(B, T, K)
    log_term = torch.full((B, T, K), -2.0)
    out = dict(log_pi=log_pi, log_term=log_term, log_cont=torch.log1p(-log_term.exp()),
               log_eta=torch.full((B, T, K), -math.log(K)), mask=torch.ones(B, T, dtype=torch.bool))  # fmt: skip
    out.update(change)
    return out


def _fit():
    return SimpleNamespace(options=OptionsMLP(2, 3, 3), option_usage=[0.5, 0.3, 0.2], duplicate_options=[])


def _split_merge(**kw):
    args = dict(fit=_fit(), refit=lambda options, seed: _fit(), score=lambda r: 0.0, num_moves=1, generator=G)
    args.update(kw)
    return split_merge(args.pop("fit"), args.pop("refit"), args.pop("score"), args.pop("num_moves"), args.pop("generator"), **args)


def _save(tmp_module, name="o.pt", **kw):
    import tempfile
    from pathlib import Path

    return save_options(tmp_module, Path(tempfile.mkdtemp()) / name, **kw)


def _tabulated(loss=None, batch=None):
    from torchrl_options.testing import planted_corridor_demonstrations

    data = planted_corridor_demonstrations(2, 5, seed=0)
    return TabulatedDDO(DDOLoss(OptionsMLP(10, 2, 2)) if loss is None else loss, data if batch is None else batch)


CASES = [
    # ---- copy_option / propose_pairs / split_merge / check_split_merge_options
    ("copy_option", "issue: victim=-1 (would overwrite the last option)", lambda: copy_option(OptionsMLP(2, 3, 4), -1, 0, G),
     ValueError, "victim must be an int in [0, 3], got -1"),
    ("copy_option", "victim past the last option", lambda: copy_option(OptionsMLP(2, 3, 4), 4, 0, G), ValueError,
     "victim must be an int in [0, 3], got 4"),
    ("copy_option", "donor negative", lambda: copy_option(OptionsMLP(2, 3, 4), 0, -2, G), ValueError, "donor must be an int in [0, 3]"),
    ("copy_option", "victim a float", lambda: copy_option(OptionsMLP(2, 3, 4), 1.0, 0, G), TypeError, "victim must be an int"),
    ("copy_option", "victim equal to donor", lambda: copy_option(OptionsMLP(2, 3, 4), 2, 2, G), ValueError,
     "victim and donor must be two different options"),
    ("copy_option", "noise negative", lambda: copy_option(OptionsMLP(2, 3, 4), 0, 1, G, noise=-0.1), ValueError,
     "noise must be a number >= 0"),
    ("copy_option", "noise NaN", lambda: copy_option(OptionsMLP(2, 3, 4), 0, 1, G, noise=NAN), ValueError, "noise must be a number"),
    ("copy_option", "generator a seed", lambda: copy_option(OptionsMLP(2, 3, 4), 0, 1, 0), TypeError,
     "generator must be a torch.Generator"),
    ("copy_option", "options not a module", lambda: copy_option(nn.Linear(2, 2), 0, 1, G), TypeError,
     "options must be an options module"),
    ("copy_option", "control: victim 3, donor 0, no noise", lambda: copy_option(OptionsMLP(2, 3, 4), 3, 0, G, noise=0.0), OK, None),
    ("propose_pairs", "issue: no option at all (ZeroDivisionError before)", lambda: propose_pairs([], [], 0), ValueError,
     "usage must hold the usage of at least 2 options"),
    ("propose_pairs", "one option", lambda: propose_pairs([1.0], [], 0), ValueError, "at least 2 options"),
    ("propose_pairs", "a NaN usage", lambda: propose_pairs([0.5, NAN], [], 0), ValueError, "usage[1] must be a number in [0, 1]"),
    ("propose_pairs", "a duplicate pair out of range", lambda: propose_pairs([0.5, 0.5], [(0, 2)], 0), ValueError,
     "duplicates must hold (i, j) pairs of options in [0, 1]"),
    ("propose_pairs", "move negative", lambda: propose_pairs([0.5, 0.5], [], -1), ValueError, "move must be an int >= 0"),
    ("propose_pairs", "usage a string", lambda: propose_pairs("0.5", [], 0), TypeError, "usage must be a sequence of numbers"),
    ("propose_pairs", "control: two options", lambda: propose_pairs([0.7, 0.3], [], 5), OK, None),
    ("split_merge", "num_moves negative", lambda: _split_merge(num_moves=-1), ValueError, "num_moves must be an int >= 0"),
    ("split_merge", "refit not callable", lambda: _split_merge(refit=3), TypeError, "refit must be a callable"),
    ("split_merge", "min_gain negative", lambda: _split_merge(min_gain=-1.0), ValueError, "min_gain must be a number >= 0"),
    ("split_merge", "generator a seed", lambda: _split_merge(generator=1), TypeError, "generator must be a torch.Generator"),
    ("split_merge", "control: one move", lambda: _split_merge(), OK, None),
    ("check_split_merge_options", "num_options 0", lambda: check_split_merge_options(OptionsMLP(2, 3, 2), 0), ValueError,
     "num_options must be an int >= 1"),
    ("check_split_merge_options", "a shared trunk", lambda: check_split_merge_options(OptionsMLP(2, 3, 2, architecture="shared"), 2),
     ValueError, "architecture 'shared' is not supported"),
    ("check_split_merge_options", "not a module", lambda: check_split_merge_options(3, 2), TypeError, "options must be an options module"),
    # ---- diagnostics
    ("options_in_use", "issue: a NaN share counted as unused", lambda: options_in_use([0.5, NAN, 0.5]), ValueError,
     "usage[1] must be a number in [0, 1], got nan"),
    ("options_in_use", "issue: shares outside [0, 1]", lambda: options_in_use([-0.5, 1.5]), ValueError,
     "usage[0] must be a number in [0, 1], got -0.5"),
    ("options_in_use", "a string", lambda: options_in_use("0.5"), TypeError, "usage must be a sequence of numbers"),
    ("options_in_use", "a bool share", lambda: options_in_use([True, False]), TypeError, "usage[0] must be a number"),
    ("options_in_use", "control: empty", lambda: options_in_use([]), OK, None),
    ("options_in_use", "control: a tensor of shares", lambda: options_in_use(torch.tensor([0.6, 0.4])), OK, None),
    ("option_diagnostics", "issue: min_usage=2 (every option reported unused)",
     lambda: option_diagnostics(log_probs(), min_usage=2.0), ValueError, "min_usage must be a number in [0, 1], got 2"),
    ("option_diagnostics", "issue: policy_tol=-1 (duplicates never reported)",
     lambda: option_diagnostics(log_probs(), policy_tol=-1), ValueError, "policy_tol must be a number >= 0, got -1"),
    ("option_diagnostics", "termination_tol NaN", lambda: option_diagnostics(log_probs(), termination_tol=NAN), ValueError,
     "termination_tol must be a number in [0, 1]"),
    ("option_diagnostics", "min_usage a string", lambda: option_diagnostics(log_probs(), min_usage="0.1"), TypeError,
     "min_usage must be a number or None"),
    ("option_diagnostics", "log_probs without the mask", lambda: option_diagnostics({k: v for k, v in log_probs().items() if k != "mask"}),
     ValueError, "log_probs lacks ['mask']"),
    ("option_diagnostics", "log_probs not a mapping", lambda: option_diagnostics([1]), TypeError, "log_probs must be a mapping"),
    ("option_diagnostics", "control: min_usage 0 and 1, policy_tol 0",
     lambda: (option_diagnostics(log_probs(), min_usage=0.0, policy_tol=0.0), option_diagnostics(log_probs(), min_usage=1)), OK, None),
    ("restart_disagreement", "tol negative", lambda: restart_disagreement([-1.0, -1.1], tol=-0.1), ValueError,
     "tol must be a number >= 0"),
    ("restart_disagreement", "a string", lambda: restart_disagreement("-1.0"), TypeError, "log_likelihoods must be a sequence"),
    ("restart_disagreement", "control: a NaN start is left out", lambda: restart_disagreement([-1.0, NAN, -1.0]), OK, None),
    # ---- save_options
    ("save_options", "not a module (an agent)", lambda: _save(3), TypeError, "options must be an options module (TensorDictModuleBase), got int"),
    ("save_options", "a hand-written TensorDict module",
     lambda: _save(__import__("tensordict.nn", fromlist=["TensorDictModule"]).TensorDictModule(nn.Linear(2, 2), ["a"], ["b"])),
     ValueError, "cannot save a TensorDictModule by configuration"),
    ("save_options", "metadata that needs pickle", lambda: _save(OptionsMLP(2, 3, 2), metadata={"f": print}), TypeError,
     "metadata['f'] is builtin_function_or_method: only plain data"),
    ("save_options", "metadata not a dict", lambda: _save(OptionsMLP(2, 3, 2), metadata=[1]), TypeError, "metadata must be None or a dict"),
    ("save_options", "meta_control not a module", lambda: _save(OptionsMLP(2, 3, 2), meta_control=3), TypeError,
     "meta_control must be None or a TensorDictModuleBase"),
    ("save_options", "control: options, meta-control and plain metadata",
     lambda: _save(OptionsMLP(2, 3, 2), meta_control=MetaControlMLP(2, 2), metadata={"a": [1, (2, "x")], "t": torch.zeros(1)}), OK, None),
    # ---- TabulatedDDO / unique_rows
    ("TabulatedDDO", "not a DDOLoss", lambda: _tabulated(loss=3), TypeError, "loss_module must be a DDOLoss"),
    ("TabulatedDDO", "batch not a TensorDict", lambda: _tabulated(batch=[1]), TypeError, "batch must be a [B, T] TensorDict"),
    ("TabulatedDDO", "control: a planted batch", lambda: _tabulated(), OK, None),
    ("unique_rows", "no column", lambda: unique_rows([]), ValueError, "columns must be a non-empty sequence of tensors"),
    ("unique_rows", "columns of different lengths", lambda: unique_rows([torch.zeros(3), torch.zeros(4)]), ValueError,
     "the columns must share their leading size N, got [3, 4]"),
    ("unique_rows", "a 0-d column", lambda: unique_rows([torch.tensor(1.0)]), TypeError, "columns[0] must be a tensor with a leading dimension"),
    ("unique_rows", "control: one column", lambda: unique_rows([torch.tensor([1, 1, 2])]), OK, None),
    # ---- UsageFloor / check_usage_floor
    ("check_usage_floor", "a floor of 1 (every option at least its uniform share: no room to move)",
     lambda: check_usage_floor(1.0), ValueError, "usage_floor must be a share of the uniform usage 1/K in (0, 1), got 1.0"),
    ("check_usage_floor", "a floor of 0", lambda: check_usage_floor(0.0), ValueError, "in (0, 1), got 0.0"),
    ("check_usage_floor", "NaN", lambda: check_usage_floor(NAN), ValueError, "usage_floor must be a number, got nan"),
    ("check_usage_floor", "a string", lambda: check_usage_floor("0.5"), TypeError, "usage_floor must be a number or None"),
    ("check_usage_floor", "a bool", lambda: check_usage_floor(True), TypeError, "usage_floor must be a number or None"),
    ("check_usage_floor", "control: None and 0.5", lambda: (check_usage_floor(None), check_usage_floor(0.5)), OK, None),
    ("UsageFloor", "num_options 0", lambda: UsageFloor(0, 0.5), ValueError, "num_options must be an int >= 1"),
    ("UsageFloor", "num_options a float", lambda: UsageFloor(2.0, 0.5), TypeError, "num_options must be an int"),
    ("UsageFloor", "floor None", lambda: UsageFloor(2, None), TypeError, "floor must be a number in (0, 1), got None"),
    ("UsageFloor", "floor above 1", lambda: UsageFloor(2, 1.5), ValueError, "floor must be a share of the uniform usage"),
    ("UsageFloor", "step negative", lambda: UsageFloor(2, 0.5, step=-1), ValueError, "step must be a positive finite number"),
    ("UsageFloor.update", "usage of the wrong size", lambda: UsageFloor(2, 0.5).update(torch.zeros(3)), ValueError,
     "usage must be a [K=2] tensor, got (3,)"),
    ("UsageFloor.update", "usage a list", lambda: UsageFloor(2, 0.5).update([0.5, 0.5]), TypeError, "usage must be a [K=2] tensor, got list"),
    ("UsageFloor.update", "a NaN usage (would make the dual NaN)", lambda: UsageFloor(2, 0.5).update(torch.tensor([NAN, 0.5])),
     ValueError, "usage must be finite"),
    ("UsageFloor", "control: two options, floor 0.5, one update", lambda: UsageFloor(2, 0.5).update(torch.tensor([0.9, 0.1])), OK, None),
]  # fmt: skip

# change_points (discovery/initialization.py): a negative action used to be read as action 0
NOT_HERE = [
    ("change_points", "issue: action -1 read as action 0",
     lambda: change_points(torch.tensor([[-1, 0, 1, 1]]), torch.ones(1, 4, dtype=torch.bool), window=1),
     ValueError, "discrete actions must be >= 0 at valid steps, got -1"),
    ("change_points", "NaN continuous action",
     lambda: change_points(torch.tensor([[[0.0], [float("nan")]]]), torch.ones(1, 2, dtype=torch.bool), window=1),
     ValueError, "NaN or infinite"),
    ("change_points", "bool actions", lambda: change_points(torch.ones(1, 4, dtype=torch.bool), torch.ones(1, 4, dtype=torch.bool)),
     TypeError, "integer (or float) actions"),
    ("change_points", "control: -1 under the mask",
     lambda: change_points(torch.tensor([[0, 0, 1, -1]]), torch.tensor([[True, True, True, False]]), window=1), OK, None),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_discovery_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)


@pytest.mark.parametrize("api, case, call, error, phrase", NOT_HERE, ids=ids(NOT_HERE))
def test_discovery_bad_inputs_of_other_modules(api, case, call, error, phrase):
    check(call, error, phrase)


def test_save_options_is_atomic(tmp_path, monkeypatch):
    """A save killed half-way leaves the previous file whole (the next run reads good options or none)."""
    from torchrl_options import load_options

    path = tmp_path / "options.pt"
    save_options(OptionsMLP(2, 3, 2), path)
    good = path.read_bytes()

    def broken(obj, f, *a, **k):
        with open(f, "wb") as out:
            out.write(b"PK\x03\x04half")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(KeyboardInterrupt):
        save_options(OptionsMLP(2, 3, 2), path)
    monkeypatch.undo()
    assert path.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["options.pt"]
    load_options(path)
