#!/usr/bin/env bash
# On a lent GPU machine (the device tool, from the repository root with .whl carried): unpack the bundle that
# benchmarks/device/bundle.sh built, then run benchmarks/gpu_check.py within BUDGET_S seconds, its JSON and log into
# $OUT. Usage: bash benchmarks/device/run.sh [BUDGET_S] [gpu_check flags...]
set -uo pipefail
budget=${1:-480}
shift || true
site=/tmp/site
mkdir -p "$site" "${OUT:=/tmp/out}"
t0=$(date +%s)
python3 -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='fully_trusted')" \
  .whl/bundle.tar.xz "$site" || { echo "run: cannot unpack .whl/bundle.tar.xz (carry it)"; exit 2; }
export PYTHONPATH="$site:$PWD" HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
echo "run: bundle unpacked in $(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 benchmarks/gpu_check.py --device cuda --budget-s "$budget" --scratch /tmp/gpu-check \
  --out "$OUT/gpu_check.json" "$@" 2>&1 | tee "$OUT/log"
