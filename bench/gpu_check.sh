#!/usr/bin/env bash
# The training reader on a GPU, in about five minutes: the torch representations' parity tests
# on CUDA, then `python -m bench.training_reader --quick` on CUDA, printed as one compact table.
#
#   bash bench/gpu_check.sh            (from anywhere; PYTHON=... picks the interpreter)
#
# Exit 0: parity passed and the bench ran; 1: a test or the bench failed; 2: no torch or no
# CUDA device to check on. What it needs installed, offline: bench/README.md.
# GPU_CHECK_DEVICE=cpu runs the same steps on the CPU (to try the script on a machine without a GPU).
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python || command -v python3)}
OUT=${GPU_CHECK_OUT:-/tmp/rigd-gpu-check}
mkdir -p "$OUT"
DEV=${GPU_CHECK_DEVICE:-cuda}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-$OUT/numba}

if ! "$PY" -c "import torch" 2>/dev/null; then
    echo "gpu_check: '$PY' cannot import torch: install a CUDA build of torch (bench/README.md), then rerun"
    exit 2
fi
if [ "$DEV" = cuda ] && ! "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "gpu_check: torch $("$PY" -c 'import torch; print(torch.__version__)') sees no CUDA device; nothing to check"
    exit 2
fi
if [ "$DEV" = cuda ]; then
    "$PY" -c "import torch; p = torch.cuda.get_device_properties(0); print(f'gpu_check: torch {torch.__version__}, {p.name}, {p.total_memory / 2**30:.0f} GiB')"
fi

echo "gpu_check: parity tests on $DEV (tests/reconstruction/test_torch_*.py)"
RIGD_TEST_TORCH_DEVICE=$DEV timeout 180 "$PY" -m pytest -q -p no:cacheprovider -o addopts="" \
    tests/reconstruction/test_torch_representations.py tests/reconstruction/test_torch_dataset.py \
    >"$OUT/parity.log" 2>&1
parity=$?
tail -n 1 "$OUT/parity.log"
if [ $parity -ne 0 ]; then
    grep -E "^(FAILED|ERROR)|Error" "$OUT/parity.log" | head -n 20
fi

echo "gpu_check: bench.training_reader --quick on $DEV (log: $OUT/bench.log)"
timeout 360 "$PY" -m bench.training_reader --quick --device "$DEV" --take-dir "$OUT/take" \
    --json "$OUT/training_reader.json" 2>"$OUT/bench.log"
bench=$?
if [ $bench -ne 0 ]; then
    echo "gpu_check: the bench failed (exit $bench); last lines of its log:"
    tail -n 15 "$OUT/bench.log"
fi
echo "gpu_check: parity $([ $parity -eq 0 ] && echo passed || echo FAILED), bench $([ $bench -eq 0 ] && echo ran || echo FAILED); results in $OUT"
[ $parity -eq 0 ] && [ $bench -eq 0 ]
