#!/usr/bin/env bash
# The GPU checks in one command, for a CUDA machine with PyTorch and Triton (e.g. a lent H100):
#   bash benchmarks/gpu_check.sh [OUT_DIR]
# If a `.whl/` folder of wheels is present (torchrl, tensordict, gymnasium, ale-py, hydra-core, omegaconf, antlr4,
# pyvers, orjson, hoptorch, importlib_metadata, farama-notifications; no internet there), they are installed first
# into /tmp/site. Runs the `gpu` tests, the Triton kernel check and timing (bench_triton_fb.py), the E-step
# benchmark against the naive loop on CUDA, and the Atari smoke preset with the networks on CUDA.
set -o pipefail
OUT_DIR=${1:-${OUT:-/tmp/gpu_check}}
mkdir -p "$OUT_DIR"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.used --format=csv
python3 -m pytest -q -p no:cacheprovider -m gpu tests 2>&1 | tee "$OUT_DIR/pytest_gpu.log" | tail -3
python3 benchmarks/bench_triton_fb.py 2>&1 | tee "$OUT_DIR/triton.log"
python3 benchmarks/bench_forward_backward.py --device cuda --shapes "4096,1000,16;64,1000,8;64,1000,32" \
  --threads 1 --backends baseline,reference,triton,auto 2>&1 | tee "$OUT_DIR/fb.log"
python3 recipes/atari_ram.py preset=smoke game=Seaquest atari.device=cuda out_dir=/tmp/gpu_check_smoke \
  > "$OUT_DIR/smoke.log" 2>&1 && echo "atari smoke on cuda: ok" || { echo "atari smoke on cuda: FAILED"; tail -20 "$OUT_DIR/smoke.log"; }
