r"""Decision-level batches for on-policy learners (PPO, A2C) over primitive actions and options.

With an :class:`~torchrl_options.transforms.OptionExecutor` in the env, the policy's action is used only at a
*decision* (a step with ``("next", "option_decision")`` set); on the other steps the running option acts and
the action the policy wrote is ignored. A policy gradient computed from step-level data is then wrong twice:
the ignored actions enter the likelihood ratio as if they had been taken, and GAE discounts every primitive step
by one ``gamma`` although the policy's time-steps are decisions of different lengths.

The policy over actions and options is a policy of the semi-Markov decision process (SMDP) whose time-steps are
decisions (Sutton, Precup and Singh, 1999). Its policy gradient is
:math:`\mathbb{E}\left[\sum_i \gamma^{\tau_i} \nabla \log \pi(o_i | s_i) A(s_i, o_i)\right]` over the decisions
``i`` (made at primitive time :math:`\tau_i`), with the SMDP advantage

.. math::

    A(s_i, o_i) = R_i + \gamma^{k_i} V(s_{i+1}) - V(s_i), \qquad
    R_i = \sum_{j=0}^{k_i - 1} \gamma^j r_{\tau_i + j},

where ``k_i`` is the number of primitive steps the decision lasted (PPO, as usual, leaves out the state weighting
:math:`\gamma^{\tau_i}`; with ``gamma = 1`` the two agree, which ``tests/test_ppo.py`` checks against the exact
gradient of a small SMDP). :class:`OnPolicyDecisions` turns each
collector batch into one entry per decision (with :class:`~torchrl_options.data.SMDPTransitions`): the root
entries of the decision step (observation, the policy's action and its log-probability), the discounted reward
``R_i``, ``steps_to_next_obs = k_i``, the observation of the next decision and the done flags of the decision's
last step. TorchRL's value estimators read ``steps_to_next_obs`` and discount with ``gamma ** k``, so TorchRL's
:class:`~torchrl.objectives.value.GAE` computes the SMDP advantages over the decisions
(:math:`\delta_i = R_i + \gamma^{k_i}(1 - \mathrm{terminated}_i) V(s_{i+1}) - V(s_i)`,
:math:`A_i = \delta_i + \gamma^{k_i} \lambda (1 - \mathrm{done}_i) A_{i+1}`), and
:class:`~torchrl.objectives.ClipPPOLoss` sees exactly the decisions the policy made.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from torchrl_options.checks import check_distinct_keys
from torchrl_options.data.smdp import _check_step_data, SMDPTransitions

__all__ = ["OnPolicyDecisions"]

_ENV_INDEX = "_on_policy_env_index"
_EVERY_STEP = "_on_policy_no_decision_key"  # absent from the data: every step is a decision


class OnPolicyDecisions:
    r"""Step-level collector batches to decision-level batches for PPO (see the module docstring).

    Call it on every batch of one collector, in order. A decision still running when a batch ends (an option
    spanning two batches) is carried over and returned, complete, with the next batch, keeping the action and
    log-probability the policy drew when it made it. Inside a batch the decisions of each env follow each other
    in time (envs one after the other), and the last decision of each env in the batch is marked
    ``("next", "done")`` and ``("next", "truncated")`` (not ``terminated``), TorchRL's convention for a cut
    trajectory: a value estimator bootstraps it with the value of its next decision's state and does not run
    from one env's decisions into the next env's. ``end_of_batch_key`` records these cuts.

    An episode that ends inside an option ends the decision there: its reward is summed up to the last step and
    a terminated episode is not bootstrapped. A truncated one is bootstrapped with the value of its last state.

    Args:
        gamma (float): the discount per primitive step, in ``[0, 1]`` (use the same in the value estimator:
            it discounts by ``gamma ** steps_to_next_obs``).

    Keyword Args:
        decision_key (NestedKey or None): the decision record of the executor whose decisions the policy makes
            (the top one of a hierarchy: ``("next", "option_decision_2")`` for a level-2 executor). Defaults to
            ``("next", "option_decision")``. ``None``: every step is a decision (an env without executor; the
            batches then only gain ``steps_to_next_obs = 1`` and the per-env cuts).
        reward_key, done_key (NestedKey): Defaults to ``("next", "reward")`` and ``("next", "done")``.
        terminated_key, truncated_key (NestedKey): Defaults to ``("next", "terminated")`` and
            ``("next", "truncated")``.
        steps_key (NestedKey): where ``k`` is written. Defaults to ``"steps_to_next_obs"`` (what TorchRL's
            value estimators read).
        end_of_batch_key (NestedKey): marks the last decision of each env in the batch. Defaults to
            ``("next", "end_of_batch")``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_options.data import OnPolicyDecisions
        >>> decisions = OnPolicyDecisions(gamma=0.5)
        >>> def batch(obs, decision, done):  # one env, reward 1 per step
        ...     n = len(obs)
        ...     return TensorDict({
        ...         "observation": torch.tensor(obs, dtype=torch.float).unsqueeze(-1),
        ...         "action": torch.zeros(n, dtype=torch.long), "action_log_prob": torch.zeros(n),
        ...         "next": {"observation": torch.tensor(obs, dtype=torch.float).unsqueeze(-1) + 1,
        ...                  "reward": torch.ones(n, 1), "option_decision": torch.tensor(decision),
        ...                  "done": torch.tensor(done).unsqueeze(-1), "terminated": torch.tensor(done).unsqueeze(-1)},
        ...     }, [n])
        >>> out = decisions(batch([0, 1, 2], [True, True, False], [False, False, False]))
        >>> out["observation"].squeeze(-1), out["steps_to_next_obs"].squeeze(-1)  # the option from s_1 goes on
        (tensor([0.]), tensor([1]))
        >>> out = decisions(batch([3, 4], [False, True], [False, True]))  # it ends at s_4: 3 steps
        >>> out["observation"].squeeze(-1), out["steps_to_next_obs"].squeeze(-1), out["next", "reward"].squeeze(-1)
        (tensor([1., 4.]), tensor([3, 1]), tensor([1.7500, 1.0000]))
        >>> out["next", "done"].squeeze(-1), out["next", "terminated"].squeeze(-1)
        (tensor([False,  True]), tensor([False,  True]))
    """

    def __init__(
        self,
        gamma: float,
        *,
        decision_key: NestedKey | None = ("next", "option_decision"),
        reward_key: NestedKey = ("next", "reward"),
        done_key: NestedKey = ("next", "done"),
        terminated_key: NestedKey = ("next", "terminated"),
        truncated_key: NestedKey = ("next", "truncated"),
        steps_key: NestedKey = "steps_to_next_obs",
        end_of_batch_key: NestedKey = ("next", "end_of_batch"),
    ):
        self.every_step = decision_key is None
        # every key names its own entry: steps_key=("next", "reward") would write the decisions' lengths over their
        # rewards, end_of_batch_key=("next", "terminated") would turn the batch cuts into terminations
        keys = check_distinct_keys(
            {**({} if decision_key is None else {"decision_key": decision_key}), "reward_key": reward_key,
             "done_key": done_key, "terminated_key": terminated_key, "truncated_key": truncated_key,
             "steps_key": steps_key, "end_of_batch_key": end_of_batch_key},
            "OnPolicyDecisions",
        )  # fmt: skip
        self._decision_key = keys.get("decision_key")
        self.smdp = SMDPTransitions(
            gamma, decision_key=_EVERY_STEP if decision_key is None else decision_key, reward_key=reward_key, done_key=done_key, steps_key=steps_key
        )
        self.smdp.owner = "OnPolicyDecisions"
        self.done_key = keys["done_key"]
        self.terminated_key = keys["terminated_key"]
        self.truncated_key = keys["truncated_key"]
        self.end_of_batch_key = keys["end_of_batch_key"]

    @property
    def gamma(self) -> float:
        """The discount per primitive step."""
        return self.smdp.gamma

    @property
    def num_pending(self) -> int:
        """Number of envs whose current decision is still running (carried over to the next batch)."""
        return self.smdp.num_pending

    def reset(self) -> None:
        """Forgets the decisions carried over (call it when the collector restarts its episodes)."""
        self.smdp.reset()

    def __call__(self, data: TensorDictBase) -> TensorDictBase:
        """Returns the decisions of ``data`` (shape ``[T]`` or ``[*B, T]``, time last) that end in it, as a
        TensorDict of shape ``[M]``; ``M`` may be 0.

        Raises:
            ValueError: ``data`` lacks the decision, done or reward entries, already holds an entry this writes
                (``steps_key``, ``end_of_batch_key``), or has another layout (envs, entries, device) than the
                previous batch while decisions are carried over from it (call :meth:`reset` to start a new stream).
        """
        _check_step_data(data, self.smdp.keys, "OnPolicyDecisions", False)
        if data.get(self.end_of_batch_key, None) is not None:
            raise ValueError(
                f"OnPolicyDecisions: the step-level data already holds a {self.end_of_batch_key!r} entry "
                "(end_of_batch_key), which the batch cuts are written to: it would be overwritten. Pass another "
                "end_of_batch_key, or remove the entry."
            )
        if not self.every_step and data.get(self._decision_key, None) is None:
            raise ValueError(
                f"OnPolicyDecisions: the data has no {self._decision_key!r} entry (decision_key). Collect with an "
                "OptionExecutor in the env, or pass the decision key of its level (e.g. ('next', "
                "'option_decision_2') for a level-2 executor)."
            )
        data = data.copy()  # shallow: the caller's batch keeps its keys
        n = data.shape[:-1].numel() if data.ndim > 1 else 1
        index = torch.arange(n, device=data.get(self.done_key).device).reshape(*data.shape[:-1], 1)
        data.set(_ENV_INDEX, index.expand(data.shape).clone())
        if data.get(self.terminated_key, None) is None:
            # the cuts below set done: keep the episode ends apart from them
            data.set(self.terminated_key, data.get(self.done_key).clone())
        if self.every_step:  # each step is a complete decision of one step
            out = data.reshape(-1)
            reward = out.get(self.smdp.keys.reward)
            out.set(self.smdp.keys.steps, torch.ones(reward.shape, dtype=torch.long, device=reward.device))
        else:
            out = self.smdp(data)
        env = out.pop(_ENV_INDEX)
        last = torch.ones_like(env, dtype=torch.bool)
        last[:-1] = env[1:] != env[:-1]
        done = out.get(self.done_key)
        cut = last.reshape(done.shape)
        out.set(self.end_of_batch_key, cut)
        out.set(self.done_key, done | cut)
        terminated = out.get(self.terminated_key).bool()
        truncated = out.get(self.truncated_key, torch.zeros_like(cut))
        out.set(self.truncated_key, truncated | (cut & ~terminated))
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}(gamma={self.gamma}, decision_key={self._decision_key!r})"
