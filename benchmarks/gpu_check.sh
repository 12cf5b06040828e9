#!/usr/bin/env bash
# The GPU checks in one command, for a CUDA machine with PyTorch and Triton (e.g. a lent H100), about 7 minutes at
# most (each step has its own timeout; the whole stays under the device tool's ten minutes per command):
#   bash benchmarks/gpu_check.sh [OUT_DIR]          # OUT_DIR defaults to $OUT (the device tool's), else /tmp/gpu_check
# If a `.whl/` folder of wheels is present (torchrl, tensordict, gymnasium, ale-py, hydra-core, omegaconf, antlr4,
# pyvers, orjson, hoptorch, importlib_metadata, farama-notifications; no internet there), they are installed first
# into /tmp/site. Steps:
#   1. the `gpu` tests (tests/test_forward_backward_fast.py: the Triton kernel against the reference;
#      tests/test_discovery_gpu.py: discovery on CUDA = on CPU, and at most 5 host synchronisations per iteration);
#   2. the Triton kernel's check and launch sweep (bench_triton_fb.py) and the E-step benchmark against the naive
#      loop and the memory floor at (4096, 1000, 16), (64, 1000, 8), (64, 1000, 32) (bench_forward_backward.py);
#   3. discovery at 1,024,000 steps (bench_discovery_scale.py): the in-memory and streamed paths with
#      device=cuda, and the in-memory path on this machine's CPU (1 thread) as the baseline, in the same run;
#   4. with SMOKE=1, the Atari smoke preset with the networks on CUDA.
# Every log lands in OUT_DIR; OUT_DIR/summary.md holds the date, the card and the tables, to be kept in
# results/gpu/ by the session that ran it (never claim a figure that is not in such a file).
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
SUMMARY="$OUT_DIR/summary.md"
CARD=$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)
{
  echo "# GPU check, $(date -u '+%Y-%m-%d %H:%M UTC'), ${CARD:-no card found}"
  echo
  echo "git commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown); $(python3 -c 'import torch; print("torch", torch.__version__, "CUDA", torch.version.cuda)')"
  echo "$(nproc) CPU cores; command: bash benchmarks/gpu_check.sh"
} > "$SUMMARY"
nvidia-smi --query-gpu=name,memory.total,memory.used --format=csv | tee -a "$SUMMARY"

step() {  # step NAME SECONDS COMMAND...: runs with a timeout, logs to OUT_DIR/NAME.log, notes the outcome
  local name=$1 seconds=$2
  shift 2
  local start=$(date +%s)
  timeout "$seconds" "$@" > "$OUT_DIR/$name.log" 2>&1
  local rc=$?
  local verdict="ok"
  [ $rc -eq 124 ] && verdict="TIMED OUT after ${seconds} s"
  [ $rc -ne 0 ] && [ $rc -ne 124 ] && verdict="FAILED (exit $rc)"
  printf '\n## %s: %s (%d s)\n\n' "$name" "$verdict" "$(( $(date +%s) - start ))" >> "$SUMMARY"
  echo "$name: $verdict"
}

step pytest_gpu 120 python3 -m pytest -q -p no:cacheprovider -m gpu tests/test_forward_backward_fast.py tests/test_discovery_gpu.py
fenced() { echo '```' >> "$SUMMARY"; "$@" >> "$SUMMARY"; echo '```' >> "$SUMMARY"; }
fenced tail -n 15 "$OUT_DIR/pytest_gpu.log"

step triton 60 python3 benchmarks/bench_triton_fb.py --shapes "4096,1000,16;64,1000,8" --variants "4,1;8,1;16,2"
fenced tail -n 30 "$OUT_DIR/triton.log"

step estep 100 python3 benchmarks/bench_forward_backward.py --device cuda --shapes "4096,1000,16;64,1000,8;64,1000,32" \
  --threads 1 --reps 3 --backends baseline,reference,triton,auto
fenced tail -n 30 "$OUT_DIR/estep.log"

step discovery_cuda 120 python3 benchmarks/bench_discovery_scale.py --sizes 1024000 --paths memory,full,minibatch \
  --iterations 5 --device cuda --workdir /tmp/bench_discovery_scale --max-gb 20
grep -E '^\||^wrote' "$OUT_DIR/discovery_cuda.log" >> "$SUMMARY"

step discovery_cpu 90 python3 benchmarks/bench_discovery_scale.py --sizes 1024000 --paths memory --iterations 3 \
  --device cpu --workdir /tmp/bench_discovery_scale --max-gb 20
grep '^|' "$OUT_DIR/discovery_cpu.log" >> "$SUMMARY"

if [ "${SMOKE:-0}" = "1" ]; then
  step atari_smoke 90 python3 recipes/atari_ram.py preset=smoke game=Seaquest atari.device=cuda out_dir=/tmp/gpu_check_smoke
fi
echo
cat "$SUMMARY"
