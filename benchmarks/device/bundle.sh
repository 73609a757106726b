#!/usr/bin/env bash
# Build .whl/bundle.tar.xz: what benchmarks/gpu_check.py imports that the lent GPU machine's image lacks (or has in
# a version lerobot 0.6.1 does not run with), unpacked site-packages, xz-compressed so that it and the tracked tree
# fit one device command's 64 MiB carry (the wheels alone are ~60 MB zipped; the bundle ~38 MB).
#
# The list is what a CPU dry run under an import blocker shows missing on the image (benchmarks/device/README.md);
# the versions are this project's .venv's, for CPython 3.12 manylinux x86-64 (the image's Python). Idempotent: a
# bundle newer than this script is kept.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=.whl/bundle.tar.xz
[ -f "$out" ] && [ "$out" -nt "$0" ] && { echo "bundle: $out is up to date"; exit 0; }
packages=(lerobot draccus gymnasium farama-notifications av dm-tree datasets multiprocess dill mergedeep
          qwen-vl-utils diffusers pytz num2words jmespath transformers tokenizers)
sdists=(docopt)  # pure Python published without a wheel (num2words needs it): built here
source benchmarks/device/cp312_wheels.sh
cp312_wheels .whl/wheels
site=$(mktemp -d)
trap 'rm -rf "$site"' EXIT
for w in .whl/wheels/*.whl; do .venv/bin/python -m zipfile -e "$w" "$site"; done
tar -C "$site" -cf - . | xz -T2 -6 > "$out.tmp"
mv "$out.tmp" "$out"
echo "bundle: $out $(du -h "$out" | cut -f1) from ${pins[*]}"
