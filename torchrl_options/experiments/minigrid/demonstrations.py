"""Demonstrations of the BabyAI bot, labelled at every step with the subgoal it is pursuing.

The BabyAI bot (Chevalier-Boisvert et al., "BabyAI", ICLR 2019; ``minigrid.utils.baby_ai_bot.BabyAIBot``) plans
with a stack of subgoals: go next to an object or a position, open a door, pick up, drop, and exploratory moves
when the target is not in sight. After ``bot.replan()`` the subgoal on top of the stack is the one the suggested
action serves: that is the step's ground-truth label, in two granularities.

**Subgoal** (the bot's own unit): its *type*, one of :data:`SUBGOAL_TYPES` (``GoNextTo``, ``Explore`` = an
exploratory ``GoNextTo``, ``Pickup``, ``Open``, ``Drop``, ``Close``), and its *target*, one of :data:`TARGETS`: the
object type it goes to or acts on (``key``, ``door``, ``box``, ``ball``, ...), or ``position`` for a cell (an
exploration waypoint, a free cell to drop a key on). ``"true_option"`` is the type and ``"true_switch"`` marks the
steps where the pair (type, target) changes: the labels of issue 50's probe. ``Pickup``, ``Open`` and ``Drop``
take one step each, so these segments are short (a boundary at 43% of the steps on ``BabyAI-UnlockPickup-v0``).

**Skill** (coarser, :data:`SKILLS`): a ``GoNextTo`` merged with the action subgoal it prepares (the subgoal
below it on the stack): "walk to the key and pick it up" is one ``pickup key`` skill, "walk to the door and open
it" one ``open door``, "walk to a free cell and drop what is carried" one ``drop key``; exploration is
``explore``, a ``GoNextTo`` that prepares nothing is ``goto <target>``. This is the granularity at which an option
terminates where the interaction ends.

Each demonstration is one episode of the bot on a level reset with its own seed, recorded through TorchRL
(:func:`~torchrl_options.envs.minigrid.make_minigrid_env`): the one-hot egocentric view and direction
(``"observation"``; what the agent carries is drawn in its own cell), the bot's action, the reward, done flags,
and the labels. Episodes the bot does not finish (it gives up on some layouts, or the step limit ends them) are
skipped and counted; the layouts are the level's resets with seeds ``first_seed, first_seed + 1, ...`` in order,
so the same call gives the same demonstrations. :func:`save_demonstrations` writes them with the package's
trajectory format (:func:`~torchrl_options.segmentation.save_trajectories`, a ``.pt`` file of tensors only).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import pad_sequence, TensorDict, TensorDictBase
from tensordict.utils import NestedKey

__all__ = [
    "BotDemonstrations",
    "bot_demonstrations",
    "load_demonstrations",
    "save_demonstrations",
    "SKILLS",
    "skill_name",
    "SUBGOAL_TYPES",
    "subgoal_name",
    "TARGETS",
    "with_previous_action",
]

logger = logging.getLogger(__name__)

_MASK = ("collector", "mask")

#: The bot's subgoal types; ``Explore`` is a ``GoNextTo`` the bot marks exploratory.
SUBGOAL_TYPES = ("GoNextTo", "Explore", "Pickup", "Open", "Drop", "Close")
#: What a subgoal goes to or acts on: ``none``, a ``position`` (a cell), or a MiniGrid object type.
TARGETS = ("none", "position", "key", "door", "box", "ball", "wall", "goal", "floor", "lava")
_OBJECTS = ("key", "door", "box", "ball")
_SKILL_VERBS = ("explore", "goto", "pickup", "open", "drop", "close")
_SKILL_OBJECTS = ("none", "key", "door", "box", "ball", "position", "other")
#: The coarse skills, ``verb object`` (index ``verb * len(objects) + object``): see the module docstring.
SKILLS = tuple(f"{v} {o}" if o != "none" else v for v in _SKILL_VERBS for o in _SKILL_OBJECTS)


def subgoal_name(subgoal_type: int, target: int) -> str:
    """``"GoNextTo key"``, ``"Pickup box"``, ...: the name of a (type, target) pair of indices.

    Examples:
        >>> subgoal_name(0, 2), subgoal_name(1, 1)
        ('GoNextTo key', 'Explore position')
    """
    return f"{SUBGOAL_TYPES[subgoal_type]} {TARGETS[target]}"


def skill_name(skill: int) -> str:
    """The name of a skill index (:data:`SKILLS`).

    Examples:
        >>> skill_name(SKILLS.index("pickup key"))
        'pickup key'
    """
    return SKILLS[skill]


def _target_index(obj_type: str | None) -> int:
    if obj_type is None:
        return TARGETS.index("none")
    return TARGETS.index(obj_type) if obj_type in TARGETS else TARGETS.index("none")


def _label_step(bot) -> tuple[int, int, int]:
    """(subgoal type, target, skill) of the subgoal on top of the bot's stack (after ``replan``)."""
    from minigrid.core.world_object import WorldObj
    from minigrid.envs.babyai.core.verifier import ObjDesc

    stack = bot.stack
    if not stack:  # the bot suggests "done": nothing left to do
        return SUBGOAL_TYPES.index("GoNextTo"), TARGETS.index("none"), SKILLS.index("goto")
    top = stack[-1]
    kind = type(top).__name__.replace("Subgoal", "")
    env = bot.mission.unwrapped

    def datum_target(sg) -> int:
        d = sg.datum
        if isinstance(d, (ObjDesc, WorldObj)):
            return _target_index(d.type)
        if d is None:
            return TARGETS.index("none")
        cell = env.grid.get(*d)  # a cell: the object on it (a blocker to move), else the position itself
        return _target_index(cell.type) if cell is not None and cell.type in _OBJECTS else TARGETS.index("position")

    def acted_on(kind: str) -> int:
        if kind in ("Open", "Close"):
            return TARGETS.index("door")
        if kind == "Drop":
            return _target_index(env.carrying.type if env.carrying is not None else None)
        fwd = env.grid.get(*(env.agent_pos + env.dir_vec))  # Pickup: the object in front of the agent
        return _target_index(fwd.type if fwd is not None else None)

    def skill(verb: str, target: int) -> int:
        name = TARGETS[target]
        obj = name if name in _SKILL_OBJECTS else "other"
        if verb == "explore":
            obj = "none"
        return _SKILL_VERBS.index(verb) * len(_SKILL_OBJECTS) + _SKILL_OBJECTS.index(obj)

    if kind == "GoNextTo":
        target = datum_target(top)
        if top.is_exploratory():
            return SUBGOAL_TYPES.index("Explore"), target, skill("explore", target)
        below = type(stack[-2]).__name__.replace("Subgoal", "") if len(stack) > 1 else None
        if below in ("Pickup", "Open", "Drop", "Close"):
            # the walk that prepares an interaction is part of that skill; what is dropped is what is carried
            obj = target if below == "Pickup" else acted_on(below)
            return SUBGOAL_TYPES.index("GoNextTo"), target, skill(below.lower(), obj)
        return SUBGOAL_TYPES.index("GoNextTo"), target, skill("goto", target)
    if kind in ("Pickup", "Open", "Drop", "Close"):
        target = acted_on(kind)
        return SUBGOAL_TYPES.index(kind), target, skill(kind.lower(), target)
    # the bot never acts with an ExploreSubgoal on top (it pushes an exploratory GoNextTo first)
    return SUBGOAL_TYPES.index("Explore"), TARGETS.index("none"), skill("explore", 0)


@dataclass
class BotDemonstrations:
    """What :func:`bot_demonstrations` returns.

    Attributes:
        data (TensorDict): ``[B, T]`` trajectories padded at the end, in the layout of
            :func:`~torchrl_options.discover_options`: ``"observation"``, ``"action"``, ``("next", "observation")``,
            ``("next", "reward")``, ``("next", "done" / "terminated" / "truncated")``, ``("collector", "mask")``, and
            the labels: ``"subgoal_type"``, ``"subgoal_target"``, ``"skill"``, ``"true_option"`` (= the type),
            ``"true_switch"`` (a new (type, target) pair starts, ``True`` at step 0), ``"skill_switch"`` (a new skill
            starts), and ``"env_seed"`` ``[B, T]`` (the layout's seed, repeated along the trajectory); the integer
            labels are -1 on padding.
        level (str): the level.
        env_seeds (list of int): the seeds of the kept episodes.
        skipped_seeds (list of int): seeds whose episode the bot did not finish.
    """

    data: TensorDict
    level: str
    env_seeds: list[int] = field(default_factory=list)
    skipped_seeds: list[int] = field(default_factory=list)

    @property
    def num_steps(self) -> int:
        return int(self.data.get(_MASK).sum())


def _switches(*labels: torch.Tensor) -> torch.Tensor:
    change = torch.zeros_like(labels[0], dtype=torch.bool)
    for x in labels:
        change[1:] |= x[1:] != x[:-1]
    change[0] = True
    return change


#: The most subgoals the bot's plan may hold, and the most it may push in one ``replan``. Its plans are a few
#: subgoals deep; on some layouts (seed 4 of ``BabyAI-UnlockToUnlock-v0`` with minigrid 3.2) one ``replan`` pushes
#: exploration subgoals without end and never returns. A deeper plan, or more pushes in one step (a cycle of pushes
#: and pops), ends the episode as one the bot gives up on.
_MAX_PLAN_DEPTH = 256


class _PlanTooDeep(RuntimeError):
    pass


class _BoundedPlan(list):
    """The bot's subgoal stack: raises :class:`_PlanTooDeep` when it would hold more than :data:`_MAX_PLAN_DEPTH`
    subgoals, or when more than that many are pushed between two calls of :meth:`new_step`."""

    pushes = 0

    def new_step(self) -> None:
        self.pushes = 0

    def append(self, subgoal) -> None:
        self.pushes += 1
        if len(self) >= _MAX_PLAN_DEPTH or self.pushes > _MAX_PLAN_DEPTH:
            raise _PlanTooDeep(f"the bot's plan passed {_MAX_PLAN_DEPTH} subgoals (or pushes in one step)")
        super().append(subgoal)


def _one_episode(env, gym_env, env_seed: int, max_steps: int | None) -> TensorDict | None:
    from minigrid.utils.baby_ai_bot import BabyAIBot, DisappearedBoxError
    from torchrl.envs.utils import step_mdp

    td = env.reset(seed=env_seed)
    try:
        bot = BabyAIBot(gym_env)
    except (AssertionError, AttributeError) as err:  # a level without BabyAI instructions
        raise ValueError(
            f"the BabyAI bot cannot plan on {gym_env.spec.id if gym_env.spec else gym_env}: it needs a BabyAI level "
            f"(BabyAI-*), whose mission it parses ({type(err).__name__}: {err})."
        ) from None
    plan = bot.stack = _BoundedPlan(bot.stack)
    limit = max_steps or gym_env.unwrapped.max_steps
    steps, labels = [], []
    try:
        for _ in range(limit):
            plan.new_step()
            action = int(bot.replan())
            labels.append(_label_step(bot))
            td.set("action", torch.tensor(action))
            td = env.step(td)
            steps.append(td.clone())
            if bool(td.get(("next", "done")).any()):
                break
            td = step_mdp(td)
    except (DisappearedBoxError, AssertionError, _PlanTooDeep):  # the bot gives up (it fails on KeyInBox, say)
        return None
    traj = torch.stack(steps)
    if not bool(traj[-1].get(("next", "terminated")).any()) or float(traj[-1].get(("next", "reward")).sum()) <= 0:
        return None  # the bot did not finish the mission within the limit
    lab = torch.tensor(labels, dtype=torch.long)
    traj.set("subgoal_type", lab[:, 0])
    traj.set("subgoal_target", lab[:, 1])
    traj.set("skill", lab[:, 2])
    traj.set("true_option", lab[:, 0].clone())
    traj.set("true_switch", _switches(lab[:, 0], lab[:, 1]))
    traj.set("skill_switch", _switches(lab[:, 2]))
    traj.set("env_seed", torch.full((traj.shape[0],), env_seed, dtype=torch.long))
    keep = ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
            ("next", "terminated"), ("next", "truncated"), "subgoal_type", "subgoal_target", "skill", "true_option",
            "true_switch", "skill_switch", "env_seed"]  # fmt: skip
    return traj.select(*keep)


def bot_demonstrations(
    level: str,
    num_demonstrations: int,
    *,
    first_seed: int = 0,
    max_steps: int | None = None,
    max_attempts: int | None = None,
    progress: bool = False,
) -> BotDemonstrations:
    """``num_demonstrations`` finished episodes of the BabyAI bot on ``level``, labelled with its subgoals.

    Deterministic: episode ``i`` is the level reset with seed ``first_seed + i`` (skipping those the bot does not
    finish). The bot plans on the full state (it is the expert); the recorded observation is the agent's one-hot
    egocentric view and direction.

    Args:
        level (str): a BabyAI level, e.g. ``"BabyAI-UnlockPickup-v0"`` (the bot parses BabyAI missions only).
        num_demonstrations (int): episodes to keep, ``>= 1``.

    Keyword Args:
        first_seed (int): the seed of the first layout. Defaults to 0.
        max_steps (int, optional): cut an episode after this many steps (it is then skipped); defaults to the
            level's own limit.
        max_attempts (int, optional): give up after this many episodes (default ``4 * num_demonstrations + 10``).
        progress (bool): a tqdm bar.

    Returns:
        BotDemonstrations: the ``[B, T]`` data (see :class:`BotDemonstrations`), the seeds kept and skipped.

    Raises:
        ValueError: a bad argument, a level the bot cannot plan on, or fewer finished episodes than asked within
            ``max_attempts``.

    Examples:
        >>> demos = bot_demonstrations("BabyAI-UnlockLocal-v0", 2)  # doctest: +SKIP
        >>> demos.data.batch_size[0], demos.data["observation"].shape[-1]  # doctest: +SKIP
        (2, 984)
    """
    from torchrl_options.checks import check_bool, check_int
    from torchrl_options.envs.minigrid import make_minigrid_env, make_minigrid_gym

    check_int(num_demonstrations, "num_demonstrations", minimum=1)
    check_int(first_seed, "first_seed", minimum=0)
    check_int(max_steps, "max_steps", minimum=1, allow_none=True)
    check_int(max_attempts, "max_attempts", minimum=1, allow_none=True)
    check_bool(progress, "progress")
    if not isinstance(level, str) or not level.startswith("BabyAI-"):
        raise ValueError(f"level must be a BabyAI level (BabyAI-*: the bot parses BabyAI missions), got {level!r}.")
    gym_env = make_minigrid_gym(level)
    env = make_minigrid_env(gym_env=gym_env)
    attempts = max_attempts if max_attempts is not None else 4 * num_demonstrations + 10
    kept, seeds, skipped = [], [], []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=num_demonstrations, desc=f"bot on {level}", unit="demo")
    seed = first_seed
    try:
        while len(kept) < num_demonstrations and seed - first_seed < attempts:
            traj = _one_episode(env, gym_env, seed, max_steps)
            if traj is None:
                skipped.append(seed)
            else:
                kept.append(traj)
                seeds.append(seed)
                if bar is not None:
                    bar.update(1)
            seed += 1
    finally:
        if bar is not None:
            bar.close()
        env.close()
    if len(kept) < num_demonstrations:
        raise ValueError(
            f"the bot finished {len(kept)} of {seed - first_seed} episodes of {level} (max_attempts={attempts}); "
            f"asked for {num_demonstrations}."
        )
    if skipped:
        logger.info("bot_demonstrations: %s: skipped %d unfinished episodes (seeds %s)", level, len(skipped), skipped[:10])
    lengths = torch.tensor([t.shape[0] for t in kept])
    data = pad_sequence(kept)
    data.set(_MASK, torch.arange(data.shape[1])[None] < lengths[:, None])
    for key in ("true_option", "subgoal_type", "subgoal_target", "skill", "env_seed"):
        data.set(key, torch.where(data.get(_MASK), data.get(key), -1))
    return BotDemonstrations(data=data, level=level, env_seeds=seeds, skipped_seeds=skipped)


def save_demonstrations(demos: BotDemonstrations | TensorDictBase, path: str | Path) -> Path:
    """Writes the ``[B, T]`` demonstrations as a ``.pt`` file of tensors only (the package's trajectory format,
    :func:`~torchrl_options.segmentation.save_trajectories`); :func:`load_demonstrations` reads it back.

    Examples:
        >>> import os, tempfile, torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.zeros(1, 3, 2), "action": torch.zeros(1, 3, dtype=torch.long),
        ...                  ("next", "observation"): torch.zeros(1, 3, 2), "skill": torch.zeros(1, 3, dtype=torch.long)},
        ...                 [1, 3])
        >>> path = save_demonstrations(td, os.path.join(tempfile.mkdtemp(), "demos.pt"))
        >>> load_demonstrations(path)["skill"].shape
        torch.Size([1, 3])
    """
    from torchrl_options.segmentation import save_trajectories

    data = demos.data if isinstance(demos, BotDemonstrations) else demos
    path = Path(path)
    if path.suffix.lower() not in (".pt", ".pth"):
        raise ValueError(f"save_demonstrations writes a .pt file (tensors only), got {path}.")
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_trajectories(data, path)


def load_demonstrations(path: str | Path) -> TensorDict:
    """Reads demonstrations written by :func:`save_demonstrations` (nothing in the file is unpickled)."""
    from torchrl_options.segmentation import load_trajectories

    return load_trajectories(path)


def stack_demonstrations(parts: Sequence[TensorDictBase]) -> TensorDict:
    """Concatenates ``[B_i, T_i]`` demonstration batches along the batch, padding to the longest (mask kept)."""
    rows = []
    for part in parts:
        mask = part.get(_MASK)
        rows += [part[i, : int(mask[i].sum())] for i in range(part.shape[0])]
    lengths = torch.tensor([r.shape[0] for r in rows])
    data = pad_sequence(rows)
    data.set(_MASK, torch.arange(data.shape[1])[None] < lengths[:, None])
    return data


def with_previous_action(data: TensorDictBase, num_actions: int = 7, *, observation_key: NestedKey = "observation"
                         ) -> TensorDictBase:
    """The demonstrations with the previous action appended to each observation, one-hot (zeros at a trajectory's
    first step), and the step's own action appended to its next observation, so that consecutive steps still chain.

    The options, their terminations and a learned meta-control then see what the agent did last: a policy can
    continue a turn without an option to remember its side, and a termination can see the action that ended a
    skill. Padding stays zero.

    Args:
        data (TensorDictBase): ``[B, T]`` demonstrations with ``observation_key`` and ``("next", observation_key)``
            ``[B, T, F]``, integer ``"action"`` ``[B, T]`` and ``("collector", "mask")``.
        num_actions (int): the size of the action set. Defaults to 7 (MiniGrid's).

    Keyword Args:
        observation_key (NestedKey): the observation. Defaults to ``"observation"``.

    Returns:
        TensorDictBase: a copy with ``[B, T, F + num_actions]`` observations (the input is not changed).

    Raises:
        ValueError: a missing key, actions that are not integers in ``0 .. num_actions - 1`` on the valid steps,
            or observations that are not ``[B, T, F]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.zeros(1, 3, 2), ("next", "observation"): torch.zeros(1, 3, 2),
        ...                    "action": torch.tensor([[2, 0, 1]]),
        ...                    ("collector", "mask"): torch.ones(1, 3, dtype=torch.bool)}, [1, 3])
        >>> out = with_previous_action(data, 3)
        >>> out["observation"][0, :, 2:].tolist()
        [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
        >>> out["next", "observation"][0, 0, 2:].tolist()  # step 0's next observation: the action it took
        [0.0, 0.0, 1.0]
    """
    from torchrl_options.checks import check_int

    check_int(num_actions, "num_actions", minimum=1)
    keys = data.keys(include_nested=True)
    next_key = ("next", *((observation_key,) if isinstance(observation_key, str) else tuple(observation_key)))
    for key in (observation_key, next_key, "action", ("collector", "mask")):
        if key not in keys:
            raise ValueError(f"data has no {key!r}: with_previous_action needs [B, T] demonstrations.")
    mask = data.get(("collector", "mask")).bool()
    obs = data.get(observation_key)
    if obs.dim() != 3 or tuple(obs.shape[:2]) != tuple(mask.shape):
        raise ValueError(f"{observation_key!r} must be [B, T, F] with [B, T] = {tuple(mask.shape)}, "
                         f"got {tuple(obs.shape)}.")
    action = data.get("action")
    if action.is_floating_point() or action.reshape(-1).numel() != mask.numel():
        raise ValueError(f"'action' must be integer [B, T] = {tuple(mask.shape)} (an index per step), got "
                         f"{action.dtype} of shape {tuple(action.shape)}.")
    action = action.reshape(mask.shape).long()
    valid = action[mask]
    if valid.numel() and (int(valid.min()) < 0 or int(valid.max()) >= num_actions):
        raise ValueError(f"'action' must be in 0..{num_actions - 1} on the valid steps, got values in "
                         f"{int(valid.min())}..{int(valid.max())}.")
    taken = torch.nn.functional.one_hot(action.clamp(0, num_actions - 1), num_actions).to(obs.dtype)
    taken = taken * mask.unsqueeze(-1).to(obs.dtype)
    previous = torch.zeros_like(taken)
    previous[:, 1:] = taken[:, :-1] * mask[:, 1:].unsqueeze(-1).to(obs.dtype)
    out = data.clone()
    out.set(observation_key, torch.cat([obs, previous], -1))
    out.set(next_key, torch.cat([data.get(next_key), taken], -1))
    return out
