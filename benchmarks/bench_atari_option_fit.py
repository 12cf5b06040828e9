"""How closely DDO's options fit their demonstrator on an Atari RAM game: one-hot byte options (the paper's encoding,
``OneHotByteOptions``) against options reading ``bytes / 255`` (``OptionsMLP``).

A short phase 1 (DQN over actions, one-hot Q-network), greedy demonstrations of it, then DDO twice on the same
demonstrations, once per option encoding (the pipeline's own phase 2, ``torchrl_options.experiments.atari``). Prints,
per encoding, the demonstrations' log-likelihood per step under the options next to the epsilon-greedy
demonstrator's own (``log(1 - eps + eps / A)``), and the gap. CPU, a few minutes on one core:

    python benchmarks/bench_atari_option_fit.py --game Pooyan --demos 10 --seeds 0 1

``--fits ITERATIONS:G_STEPS:LR:BATCH[:CELLS] ...`` fits several DDO settings on the same demonstrations (``BATCH`` a
number of trajectories per iteration, or ``all``; ``CELLS`` the options' hidden sizes as ``64x64x64``, ``--cells`` when
left out), e.g. the Atari recipe's phase 2 (``500:1:0.001:20``) against more G-steps; ``--encodings one_hot`` leaves
out the ``bytes`` options.

``--config <run>/config.yaml`` replays a recipe run's phase 1 instead of the script's own short one: its ``atari``
settings as the recipe ran them (vector env, checkpoints, Adam), ``--seeds`` its seeds, so the demonstrations are
the run's own, and the fits can be set against the ``phase2.json`` the run kept:

    python benchmarks/bench_atari_option_fit.py --game Gopher --seeds 0 --encodings one_hot \
        --config results/atari_cpu_vec_paper_env_8seeds/config.yaml --fits 150:1:0.005:all:32x32 500:1:0.003:20:32x32
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import torch

from torchrl_options.discovery import options_in_use
from torchrl_options.experiments.atari import AtariConfig
from torchrl_options.experiments.atari.pipeline import _phase2, _train_episodes
from torchrl_options.experiments.atari.utils import _close, _make_agent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--game", default="Pooyan")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--phase1-episodes", type=int, default=20)
    parser.add_argument("--max-steps", type=int, default=200, help="episode and demonstration cap (steps)")
    parser.add_argument("--demos", type=int, default=10)
    parser.add_argument("--ddo-iterations", type=int, default=100)
    parser.add_argument("--ddo-m-steps", type=int, default=5)
    parser.add_argument("--ddo-lr", type=float, default=0.005)
    parser.add_argument("--cells", type=int, nargs="+", default=[64, 64])
    parser.add_argument("--env-semantics", default="project", choices=["project", "paper"])
    parser.add_argument("--encodings", nargs="+", default=["one_hot", "bytes"], choices=["one_hot", "bytes"])
    parser.add_argument("--fits", nargs="+", default=None, metavar="ITERATIONS:G_STEPS:LR:BATCH[:CELLS]",
                        help="DDO settings fitted on the same demonstrations (default: the --ddo-* flags, full batch)")
    parser.add_argument("--config", default=None, metavar="CONFIG_YAML",
                        help="a recipe run's config.yaml: replay its phase 1 (its atari settings) instead of the "
                             "script's own (--phase1-episodes, --max-steps, --demos, --env-semantics are then ignored)")
    args = parser.parse_args()
    fits = ([_parse_fit(f, tuple(args.cells)) for f in args.fits] if args.fits
            else [(args.ddo_iterations, args.ddo_m_steps, args.ddo_lr, None, tuple(args.cells))])  # fmt: skip
    run_settings = _run_settings(args.config) if args.config else None
    torch.set_num_threads(1)
    # the run's own settings with --config, else a short phase 1 of the script's own
    base = dict(run_settings) if run_settings is not None else dict(
        env_semantics=args.env_semantics, max_episode_steps=args.max_steps, noop_max=5,
        phase1_episodes=args.phase1_episodes, num_demonstrations=args.demos, demo_max_steps=args.max_steps,
        options_num_cells=tuple(args.cells), ddo_iterations=args.ddo_iterations, ddo_batch_size=None,
        ddo_lr=args.ddo_lr, ddo_m_steps=args.ddo_m_steps, hidden_sizes=(64, 64, 64), lr=1e-3,
        learning_starts=200, frames_per_batch=64, updates_per_batch=4, hard_update_interval=200,
        checkpoint_every=0, demo_random_episodes=5)  # fmt: skip
    for iterations, m_steps, lr, batch, cells in fits:  # every fit's settings checked before minutes of phase 1
        try:
            AtariConfig(**dict(base, ddo_iterations=iterations, ddo_m_steps=m_steps, ddo_lr=lr, ddo_batch_size=batch,
                               options_num_cells=cells))  # fmt: skip
        except (TypeError, ValueError) as err:
            raise SystemExit(f"--fits: {err}") from None
    rows = []
    for seed in args.seeds:
        agent = _make_agent(args.game, AtariConfig(**base), seed, "actions")
        t0 = time.time()
        with tempfile.TemporaryDirectory() as d:  # the run's checkpoints every N episodes (resuming restarts there)
            _train_episodes(agent, base["phase1_episodes"], os.path.join(d, "phase1.partial.pt"), AtariConfig(**base))
        t1 = time.time() - t0
        for iterations, m_steps, lr, batch, cells in fits:
            fit = dict(base, ddo_iterations=iterations, ddo_m_steps=m_steps, ddo_lr=lr, ddo_batch_size=batch,
                       options_num_cells=cells)  # fmt: skip
            for encoding in args.encodings:
                config = AtariConfig(**dict(fit, option_encoding=encoding))
                with tempfile.TemporaryDirectory() as d:
                    t0 = time.time()
                    _, meta = _phase2(args.game, config, seed, d, agent)
                label = f"{iterations}:{m_steps}:{lr:g}:{batch or 'all'}:{'x'.join(map(str, cells))}"
                rows.append((seed, encoding, label, meta, time.time() - t0, t1))
        _close(agent)
    source = f"the run of {args.config}" if args.config else f"env {args.env_semantics}"
    print(f"\n{args.game}, {base['num_demonstrations']} greedy demonstrations of <= {base['demo_max_steps']} steps after "
          f"{base['phase1_episodes']} DQN episodes ({source}); DDO fits as iterations:G-steps:lr:batch:hidden\n")
    print("| seed | options | DDO fit | K | demo steps | options: log-lik / step | demonstrator's own | gap (nats/step) | "
          "within 0.05 | demo mean return | random policy's | options in use | DDO s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for seed, encoding, label, meta, seconds, _ in rows:
        ll, own = meta["options_log_likelihood_per_step"], meta["demonstrator_log_likelihood_per_step"]
        demo = sum(meta["demo_returns"]) / len(meta["demo_returns"])
        rand = sum(meta["random_returns"]) / max(len(meta["random_returns"]), 1)
        print(f"| {seed} | {encoding} | {label} | {meta['num_options']} | {meta['demo_frames']} | {ll:.4f} | {own:.4f} | "
              f"{own - ll:.4f} | {'yes' if ll >= own - 0.05 else 'no'} | {demo:.1f} | {rand:.1f} | "
              f"{options_in_use(meta['option_usage']) if meta.get('option_usage') else '-'} | "
              f"{seconds:.0f} |")


def _parse_fit(text: str, cells: tuple[int, ...]) -> tuple[int, int, float, int | None, tuple[int, ...]]:
    parts = text.split(":")
    try:
        if len(parts) not in (4, 5):
            raise ValueError
        batch = None if parts[3] == "all" else int(parts[3])
        if len(parts) == 5:
            cells = tuple(int(c) for c in parts[4].split("x"))
        return int(parts[0]), int(parts[1]), float(parts[2]), batch, cells
    except ValueError:
        raise SystemExit(
            f"--fits: expected ITERATIONS:G_STEPS:LR:BATCH[:CELLS] (BATCH a number or 'all', CELLS like 64x64), got {text!r}."
        )


def _run_settings(path: str) -> dict:
    """The ``atari`` settings of a recipe run's ``config.yaml`` (OmegaConf: no code runs on load)."""
    from omegaconf import OmegaConf

    if not os.path.isfile(path):
        raise SystemExit(f"--config: no file {path!r} (expected a recipe run's config.yaml).")
    try:
        config = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as err:  # YAML syntax, interpolation
        raise SystemExit(f"--config: {path!r} is not a readable config.yaml ({type(err).__name__}: {err}).") from None
    settings = config.get("atari") if isinstance(config, dict) else None
    if not isinstance(settings, dict):
        raise SystemExit(f"--config: {path!r} has no 'atari' section (expected a recipe run's config.yaml).")
    try:
        AtariConfig.from_dict(settings)  # names a setting this version does not know, or a bad value
    except (TypeError, ValueError) as err:
        raise SystemExit(f"--config: {path!r}: {err}") from None
    return {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()}


if __name__ == "__main__":
    main()
