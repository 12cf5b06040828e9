"""Bad inputs of torchrl_options.inference and torchrl_options.hierarchy (issue 53): marginals of the wrong rank,
masks of another shape, dtype or device (a "meta" tensor stands in for a GPU one), levels and options outside a
hierarchy, files that are not hierarchies. One row per case, controls included."""
import pytest
import torch

from _bad_inputs import check, ids, OK
from torchrl_options import OptionsMLP
from torchrl_options.hierarchy import (
    hierarchical_forward_backward,
    load_hierarchy,
    OptionHierarchy,
    save_hierarchy,
    stack_shapes,
)
from torchrl_options.inference import check_forward_backward_inputs, forward_backward, most_likely_options, viterbi

NAN = float("nan")
X = torch.zeros(2, 3, 4)
U = torch.rand(2, 3, 4)
MASK = torch.ones(2, 3, dtype=torch.bool)


def hierarchy(levels=1):
    h = OptionHierarchy(3, [OptionsMLP(2, 3, 2)])
    if levels == 2:
        h.append(OptionsMLP(2, 5, 2))
    return h


CASES = [
    # ---- most_likely_options
    ("most_likely_options", "issue: marginals of rank 2", lambda: most_likely_options(torch.rand(3, 4)), ValueError,
     "u must be a 3-dimensional tensor, got shape [3, 4]"),
    ("most_likely_options", "issue: marginals of rank 4", lambda: most_likely_options(torch.rand(3, 4, 2, 2)), ValueError,
     "u must be a 3-dimensional tensor, got shape [3, 4, 2, 2]"),
    ("most_likely_options", "a list", lambda: most_likely_options([[[0.1, 0.9]]]), TypeError, "u must be a torch.Tensor"),
    ("most_likely_options", "integer marginals", lambda: most_likely_options(torch.ones(2, 3, 4, dtype=torch.long)), ValueError,
     "u must be a floating point tensor"),
    ("most_likely_options", "no option (K = 0)", lambda: most_likely_options(torch.rand(2, 3, 0)), ValueError, "K >= 1 options"),
    ("most_likely_options", "NaN marginals", lambda: most_likely_options(torch.full((2, 3, 4), NAN)), ValueError,
     "u holds NaN at (b, t) = (0, 0)"),
    ("most_likely_options", "a mask of another shape", lambda: most_likely_options(U, torch.ones(2, 4, dtype=torch.bool)), ValueError,
     "mask must have shape [2, 3], got shape [2, 4]"),
    ("most_likely_options", "a float mask", lambda: most_likely_options(U, torch.ones(2, 3)), ValueError, "mask must be a bool tensor"),
    ("most_likely_options", "a mask on another device", lambda: most_likely_options(U, MASK.to("meta")), ValueError,
     "mask is on device meta but u is on device cpu"),
    ("most_likely_options", "control: NaN on padding only",
     lambda: most_likely_options(torch.cat([U[:, :2], torch.full((2, 1, 4), NAN)], 1), torch.tensor([[1, 1, 0]] * 2).bool()), OK, None),
    ("most_likely_options", "control: no mask", lambda: most_likely_options(U), OK, None),
    # ---- forward_backward / viterbi / check_forward_backward_inputs (older checks, tried again)
    ("forward_backward", "a mask on a device it cannot be moved from", lambda: forward_backward(X, X, X, X, MASK.to("meta")),
     ValueError, "mask is on device meta but log_pi is on cpu"),
    ("forward_backward", "log_term on another device", lambda: forward_backward(X, X.to("meta"), X, X), ValueError,
     "log_term is on meta but log_pi is on cpu"),
    ("forward_backward", "unknown backend", lambda: forward_backward(X, X, X, X, backend="gpu"), ValueError, "backend must be one of"),
    ("forward_backward", "NaN log-probability", lambda: forward_backward(torch.full((2, 3, 4), NAN), X, X, X), ValueError,
     "log_pi contains NaN or +inf"),
    ("forward_backward", "a mask that is not a prefix", lambda: forward_backward(X, X, X, X, torch.tensor([[1, 0, 1]] * 2).bool()),
     ValueError, "mask must mark a prefix of each row"),
    ("forward_backward", "empty batch", lambda: forward_backward(X[:0], X[:0], X[:0], X[:0]), ValueError, "empty batch"),
    ("forward_backward", "terminal a string", lambda: forward_backward(X, X, X, X, terminal="yes"), ValueError,
     "terminal must be a bool or a bool tensor"),
    ("forward_backward", "control: a terminal tensor", lambda: forward_backward(X, X, X, X, MASK, torch.tensor([True, False])), OK, None),
    ("viterbi", "rank-2 inputs", lambda: viterbi(X[0], X[0], X[0], X[0]), ValueError, "log_pi must have shape [B, T, K]"),
    ("viterbi", "unknown backend", lambda: viterbi(X, X, X, X, backend="fast"), ValueError, "backend must be one of"),
    ("viterbi", "a float mask", lambda: viterbi(X, X, X, X, torch.ones(2, 3)), ValueError, "mask must be a bool tensor"),
    ("viterbi", "control: defaults", lambda: viterbi(X, X, X, X), OK, None),
    ("check_forward_backward_inputs", "integer log-probabilities",
     lambda: check_forward_backward_inputs(*(torch.zeros(2, 3, 4, dtype=torch.long),) * 4), ValueError, "must be a floating point tensor"),
    ("check_forward_backward_inputs", "shapes that differ", lambda: check_forward_backward_inputs(X, X[:, :2], X, X), ValueError,
     "log_term has shape (2, 2, 4) but log_pi has shape (2, 3, 4)"),
    # ---- OptionHierarchy
    ("OptionHierarchy.option_index", "issue: a level past the last one", lambda: hierarchy().option_index(2, 0), ValueError,
     "level must be in [1, 1] (the hierarchy's levels), got 2"),
    ("OptionHierarchy.option_index", "level 0 (read the last level before)", lambda: hierarchy().option_index(0, 0), ValueError,
     "level must be in [1, 1]"),
    ("OptionHierarchy.option_index", "level -1", lambda: hierarchy().option_index(-1, 0), ValueError, "level must be in [1, 1]"),
    ("OptionHierarchy.option_index", "an option past the level's", lambda: hierarchy().option_index(1, 2), ValueError,
     "level 1 has 2 options (0 .. 1), got option 2"),
    ("OptionHierarchy.option_index", "option a string", lambda: hierarchy().option_index(1, "0"), TypeError, "option must be an int"),
    ("OptionHierarchy.option_index", "control: the second level", lambda: hierarchy(2).option_index(2, 1), OK, None),
    ("OptionHierarchy.options", "level a float", lambda: hierarchy().options(1.0), TypeError, "level must be an int (1-based)"),
    ("OptionHierarchy.options", "a hierarchy without levels", lambda: OptionHierarchy(3).options(1), ValueError,
     "the hierarchy has no level yet"),
    ("OptionHierarchy.meta_control", "level past the last", lambda: hierarchy().meta_control(3), ValueError, "level must be in [1, 1]"),
    ("OptionHierarchy", "num_actions a bool", lambda: OptionHierarchy(True), ValueError, "num_actions must be a positive int"),
    ("OptionHierarchy", "levels a string", lambda: OptionHierarchy(3, "ab"), TypeError, "levels must be a sequence of options modules"),
    ("OptionHierarchy", "levels a single module", lambda: OptionHierarchy(3, OptionsMLP(2, 3, 2)), TypeError,
     "levels must be a sequence"),
    ("OptionHierarchy", "a level that is not a module", lambda: OptionHierarchy(3, [3]), TypeError,
     "level 1: the options must be a TensorDictModuleBase"),
    ("OptionHierarchy", "num_options a bool", lambda: OptionHierarchy(3, [OptionsMLP(2, 3, 2)], num_options=[True]), ValueError,
     "cannot tell how many options"),
    ("OptionHierarchy", "a meta-control that is not a module", lambda: OptionHierarchy(3, [OptionsMLP(2, 3, 2)], meta_controls=[3]),
     TypeError, "meta_control must be None or a TensorDictModuleBase"),
    ("OptionHierarchy", "a level over another action space", lambda: OptionHierarchy(3, [OptionsMLP(2, 4, 2)]), ValueError,
     "level 1 options have num_actions=4"),
    ("OptionHierarchy.append", "a plain torch module", lambda: OptionHierarchy(3).append(torch.nn.Linear(2, 2), num_options=2),
     TypeError, "the options must be a TensorDictModuleBase"),
    ("OptionHierarchy", "control: two levels", lambda: hierarchy(2), OK, None),
    ("save_hierarchy", "not a hierarchy", lambda: save_hierarchy(OptionsMLP(2, 3, 2), "h.pt"), TypeError,
     "hierarchy must be an OptionHierarchy, got OptionsMLP"),
    ("stack_shapes", "no level", lambda: stack_shapes(0), ValueError, "num_levels must be an int >= 1"),
    ("stack_shapes", "a string", lambda: stack_shapes("2"), TypeError, "num_levels must be an int"),
    ("stack_shapes", "control: one level", lambda: stack_shapes(1), OK, None),
    ("hierarchical_forward_backward", "log_pi of one level without the action dimension",
     lambda: hierarchical_forward_backward(torch.zeros(2, 3, dtype=torch.long), [X], [X], [X], X), ValueError,
     "log_pi[0] must be a floating point [B, T, K_1, A] tensor"),
    ("hierarchical_forward_backward", "log_pi not a list", lambda: hierarchical_forward_backward(torch.zeros(2, 3), X, [X], [X], X),
     ValueError, "log_pi must be a non-empty list"),
]  # fmt: skip


@pytest.mark.parametrize("api, case, call, error, phrase", CASES, ids=ids(CASES))
def test_inference_and_hierarchy_bad_inputs(api, case, call, error, phrase):
    check(call, error, phrase)


def test_save_hierarchy_refuses_a_directory_and_is_atomic(tmp_path):
    with pytest.raises(ValueError, match="expected a file name for the hierarchy file, got a directory"):
        save_hierarchy(hierarchy(), tmp_path)
    with pytest.raises(ValueError, match="the folder .* does not exist"):
        save_hierarchy(hierarchy(), tmp_path / "nowhere" / "h.pt")
    save_hierarchy(hierarchy(2), tmp_path / "h.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["h.pt"]  # no temporary file left behind
    assert load_hierarchy(tmp_path / "h.pt").num_options == [2, 2]
