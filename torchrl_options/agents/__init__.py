"""Agents built from the package's pieces: DQN and PPO over primitive actions and options."""
from torchrl_options.agents.dqn import DQNHyperParameters, OptionsDQN, OptionsDQNConfig, TrainingLog
from torchrl_options.agents.ppo import OptionsPPO, OptionsPPOConfig
from torchrl_options.agents.warm_start import widen_action_rows, widen_action_values

__all__ = ["DQNHyperParameters", "OptionsDQN", "OptionsDQNConfig", "OptionsPPO", "OptionsPPOConfig", "TrainingLog", "widen_action_rows", "widen_action_values"]
