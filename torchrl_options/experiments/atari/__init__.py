"""The Atari RAM experiment of the DDO paper (figure 3) as a resumable per-cell pipeline, and its summary.

Fox, Krishnan, Stoica, Goldberg, "Multi-Level Discovery of Deep Options", 2017, section 5.2: DQN with primitive
actions for N episodes; 100 greedy trajectories of that DQN; DDO with K options per game; then DQN over actions
and options from a reset Q-function, against the baseline that continues the first DQN with actions only.

A cell is ``(game, condition, seed)``. The conditions: ``"A"``, the baseline (phase 1's DQN continued with actions
only); ``"H1"``, the paper's (actions + options, Q-function reset); and others that the paper does not run:
``"A0"``, a control (actions only, Q-function reset: what the reset alone costs); ``"H1w"``, options added
to phase 1's DQN without a reset (:meth:`~torchrl_options.agents.OptionsDQN.warm_start_from`); ``"H1g"``, as
``H1`` but each option acts with the argmax of its control policy instead of sampling from it. (DDO fits
stochastic policies to a deterministic demonstrator, the greedy phase-1 DQN; a short fit leaves them far from
deterministic, so a sampled option also explores, where the paper's argument is that options carry the
demonstrator's behaviour uninterrupted by exploration.) And ``"H1i"``, as ``H1`` but the Q-function also learns
its primitive actions' values from the steps that options take (``OptionsDQNConfig.intra_option_actions``): under
``H1`` the steps inside options, often half of all steps, teach the primitive actions nothing, where ``A0`` learns
from every step. ``"H1s"``: as ``H1``, but the options' values are also learned from every step they run, the rest
of each run being a sample of starting the option there (``OptionsDQNConfig.option_suffixes``). The letters
combine, in the order ``w``, ``g``, ``i``, ``s``: ``"H1wi"`` is the warm start with intra-option transitions,
``"H1is"`` learns both kinds of values from every step (all in :data:`CONDITIONS`). The paper's comparison is ``H1``
against ``A``.
The conditions of a seed share phases 1 and 2, cached in ``<out>/<game>/seed<s>/`` (a file lock makes later cells
wait for, then reuse, the first one's phase-1 checkpoint and options). Every phase checkpoints at its end and
every ``checkpoint_every`` episodes, and resumes from there.

What a cell returns (one row per episode in ``results.csv``): the phase-1 episodes followed by the phase-3
episodes, so both conditions have ``phase1_episodes + phase3_episodes`` episodes and share the first part.
``frames`` is the cumulative number of env steps (agent steps; ``frame_skip`` emulator frames each) at the end of
each episode, counted from the start of phase 1; for the options conditions (``H1...``) it includes the frames of

The package, by job: :mod:`~torchrl_options.experiments.atari.conditions` (the conditions' names and a sweep's
cells), :mod:`~torchrl_options.experiments.atari.config` (:class:`AtariConfig`),
:mod:`~torchrl_options.experiments.atari.pipeline` (:func:`run_atari_cell`, resumable),
:mod:`~torchrl_options.experiments.atari.figures` (figure 4) and :mod:`~torchrl_options.experiments.atari.summary`
(statistics and Markdown); :mod:`~torchrl_options.experiments.atari.utils` builds the envs and agents.
"""
from torchrl_options.experiments.atari.conditions import atari_cells, CONDITIONS, OPTION_FLAGS
from torchrl_options.experiments.atari.config import AtariConfig, store_atari_config
from torchrl_options.experiments.atari.figures import write_option_frames
from torchrl_options.experiments.atari.pipeline import option_usage, run_atari_cell
from torchrl_options.experiments.atari.summary import (
    atari_aggregates,
    atari_comparison,
    atari_scores,
    atari_summary_markdown,
    atari_summary_pairs,
    AtariComparison,
    demonstration_fit_markdown,
    greedy_evaluation_markdown,
    option_usage_markdown,
)

__all__ = [
    "AtariConfig",
    "run_atari_cell",
    "atari_cells",
    "atari_comparison",
    "atari_summary_markdown",
    "write_option_frames",
    "option_usage",
    "option_usage_markdown",
    "greedy_evaluation_markdown",
    "demonstration_fit_markdown",
    "atari_summary_pairs",
    "atari_scores",
    "atari_aggregates",
    "AtariComparison",
    "CONDITIONS",
    "OPTION_FLAGS",
    "store_atari_config",
]
