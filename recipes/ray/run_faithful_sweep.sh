#!/usr/bin/env bash
# The paper-scale Atari sweep on a running Ray cluster (recipes/ray/atari_faithful.yaml): the `faithful` preset
# (the authors' env, one-hot options, per-decision discount, 100 demonstrations, 50 greedy rollouts every 100
# episodes; 1000 + 4000 episodes vs 5000; 5 games x 50 seeds x A and H1) on CPU workers, one cell per CPU.
# Resumable: run it again to finish an interrupted sweep. Extra arguments are Hydra overrides, e.g. "seeds=[0,1]".
set -euo pipefail
OUT_DIR=${OUT_DIR:-/mnt/ddo/atari_faithful}
exec python recipes/atari_ram.py preset=faithful sweep.backend=ray sweep.ray_address=auto \
  sweep.threads_per_worker=1 atari.device=cpu atari.torch_threads=1 out_dir="$OUT_DIR" "$@"
