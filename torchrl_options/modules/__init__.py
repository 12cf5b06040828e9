"""Options and meta-control policies as TensorDict modules."""
from torchrl_options.modules._features import hidden_sizes
from torchrl_options.modules.byte_options import OneHotByteOptions
from torchrl_options.modules.grid_options import GridConvOptions
from torchrl_options.modules.meta_control import MetaControlMLP, UniformMetaControl
from torchrl_options.modules.options import GaussianOptionsMLP, OptionsMLP

__all__ = [
    "GaussianOptionsMLP",
    "GridConvOptions",
    "hidden_sizes",
    "MetaControlMLP",
    "OneHotByteOptions",
    "OptionsMLP",
    "UniformMetaControl",
]
