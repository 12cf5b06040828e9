"""torchrl-options: options (temporally extended actions) for TorchRL, and DDO (Fox et al., 2017)."""
from torchrl_options.inference import forward_backward, ForwardBackwardOutput

__version__ = "0.1.0"
__all__ = ["forward_backward", "ForwardBackwardOutput"]
