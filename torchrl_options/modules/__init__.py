"""Options and meta-control policies as TensorDict modules."""
from torchrl_options.modules.byte_options import OneHotByteOptions
from torchrl_options.modules.grid_options import GridConvOptions
from torchrl_options.modules.meta_control import MetaControlMLP, UniformMetaControl
from torchrl_options.modules.options import GaussianOptionsMLP, OptionsMLP

__all__ = ["GaussianOptionsMLP", "GridConvOptions", "MetaControlMLP", "OneHotByteOptions", "OptionsMLP", "UniformMetaControl"]
