"""Exact inference over the options' latent chain: the E-step of DDO and decoding."""
from torchrl_options.inference.forward_backward import (
    check_forward_backward_inputs,
    forward_backward,
    ForwardBackwardOutput,
)
from torchrl_options.inference.viterbi import most_likely_options, viterbi, ViterbiOutput

__all__ = [
    "check_forward_backward_inputs",
    "forward_backward",
    "ForwardBackwardOutput",
    "most_likely_options",
    "viterbi",
    "ViterbiOutput",
]
