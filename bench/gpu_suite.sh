#!/usr/bin/env bash
# The GPU test suite and the GPU benchmarks, in one command, on a machine with a GPU:
#   bash bench/gpu_suite.sh [LOGDIR]
# Logs: LOGDIR/gpu_tests.log, LOGDIR/bench_gpu.log (default LOGDIR: ./gpu-logs).
# Extra bench_gpu.py options via BENCH_ARGS, e.g. BENCH_ARGS="--gpus 1,2".
set -uo pipefail
cd "$(dirname "$0")/.."
logs="${1:-gpu-logs}"
mkdir -p "$logs"
export PYTHONUNBUFFERED=1  # sarship must be installed (pip install -e .[gpu])
nvidia-smi -L | tee "$logs/gpus.txt"
python3 -m pytest -q -m gpu -p no:cacheprovider tests/ 2>&1 | tee "$logs/gpu_tests.log"  # every gpu-marked test
tests_rc=${PIPESTATUS[0]}
# shellcheck disable=SC2086
python3 bench/bench_gpu.py ${BENCH_ARGS:-} 2>&1 | tee "$logs/bench_gpu.log"
bench_rc=${PIPESTATUS[0]}
echo "gpu tests exit $tests_rc, bench exit $bench_rc"
exit $(( tests_rc != 0 ? tests_rc : bench_rc ))
