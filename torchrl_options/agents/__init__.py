"""Agents built from the package's pieces: DQN over primitive actions and options."""
from torchrl_options.agents.dqn import OptionsDQN, OptionsDQNConfig, TrainingLog

__all__ = ["OptionsDQN", "OptionsDQNConfig", "TrainingLog"]
