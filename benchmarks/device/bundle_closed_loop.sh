#!/usr/bin/env bash
# Build .whl/closed_loop.tar.xz: what gpu_check's closed-loop stage needs on a lent GPU machine beyond its image and
# bundle A (benchmarks/device/bundle.sh): the simulator (mujoco, robosuite, hf-libero, bddl and their small needs),
# polars and zarr (the rollout's results and cache layers), with robosuite's and hf-libero's data trimmed to the
# files a rollout of the cells opens (benchmarks/device/closed_loop_files.txt, LIBERO's assets among them), and the
# cells themselves. Its members are relative to /tmp, where benchmarks/device/run_closed_loop.sh unpacks them:
# site/ (the packages, beside bundle A's) and closed_loop/cells/ (cells.origin: where they were made, since their
# exports name their base policy by that absolute path).
#
# It is larger than one device call's carry leaves beside the tracked tree, so it is also cut into N equal parts,
# .whl/closed_loop.tar.xz.KofN, each at most PART_MIB (default 43) MiB: carry one or more per call, back to back on
# the warm machine, whose /tmp keeps them; run_closed_loop.sh joins them once all are there.
#
# Usage: bash benchmarks/device/bundle_closed_loop.sh [CELLS]. CELLS: a folder benchmarks/closed_loop_cells.py made
# (default: one made at /tmp/closed_loop/cells, the path the device unpacks them at, so no link is needed there).
# The packages are this project's .venv's versions, as CPython 3.12 manylinux x86-64 wheels (the image's Python);
# the list is what benchmarks/device/trace_closed_loop_files.py prints as imported beyond the image and bundle A,
# less what is imported only where present (checked by benchmarks/device/check_closed_loop_bundle.py). Idempotent:
# a bundle newer than this script, the file list and the cells is kept.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=.whl/closed_loop.tar.xz
list=benchmarks/device/closed_loop_files.txt
cells=${1:-/tmp/closed_loop/cells}
part_mib=${PART_MIB:-43}
packages=(polars polars-runtime-32 mujoco glfw pyopengl robosuite hf-libero future easydict termcolor zarr numcodecs
          donfig msgspec google-crc32c)
sdists=(bddl)  # published without a wheel: built here (pure Python)
if [ ! -f "$cells/results.parquet" ]; then
  [ -n "${1:-}" ] && { echo "bundle: $cells holds no results.parquet (make it with benchmarks/closed_loop_cells.py)"; exit 2; }
  .venv/bin/python benchmarks/closed_loop_cells.py "$cells"
fi
if [ -f "$out" ] && [ "$out" -nt "$0" ] && [ "$out" -nt "$list" ] && [ "$out" -nt "$cells/results.parquet" ]; then
  echo "bundle: $out is up to date"; exit 0
fi
source benchmarks/device/cp312_wheels.sh
cp312_wheels .whl/closed_loop_wheels
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
site=$stage/site
for p in "${pins[@]}"; do
  name=$(echo "${p%%==*}" | tr - _)
  wheel=$(ls .whl/closed_loop_wheels/"$name"-"${p##*==}"-*.whl 2>/dev/null | head -1)
  [ -n "$wheel" ] || { echo "bundle: no wheel of $p in .whl/closed_loop_wheels"; exit 2; }
  .venv/bin/python -m zipfile -e "$wheel" "$site"
done
# robosuite's, hf-libero's and bddl's data: only the listed files, copied from the installed packages (the same versions;
# hf-libero's assets come from its installed assets folder, which its wheel lacks)
installed=$(.venv/bin/python -c "import importlib.util as u, pathlib; print(pathlib.Path(u.find_spec('robosuite').origin).parents[1])")
find "$site/robosuite" "$site/libero" "$site/bddl" -type f ! -name '*.py' -delete
while read -r f; do
  mkdir -p "$site/$(dirname "$f")"
  cp -L "$installed/$f" "$site/$f"
done < "$list"
# the cells: their cache folders trimmed to their group metadata, the one file of them a rollout reads
mkdir -p "$stage/closed_loop"
cp -r "$cells" "$stage/closed_loop/cells"
find "$stage/closed_loop/cells/cache" -mindepth 2 -maxdepth 2 ! -name zarr.json -exec rm -rf {} +
realpath "$cells" > "$stage/closed_loop/cells.origin"
tar -C "$stage" -cf - site closed_loop | xz -T2 -6 > "$out.tmp"
mv "$out.tmp" "$out"
rm -f "$out".*of*
size=$(stat -c %s "$out")
n=$(( (size + part_mib * 1048576 - 1) / (part_mib * 1048576) ))
split -n "$n" -d -a 1 --numeric-suffixes=1 "$out" "$out.part"
for k in $(seq 1 "$n"); do mv "$out.part$k" "$out.${k}of$n"; done
echo "bundle: $out $(du -h "$out" | cut -f1) in $n part(s) of $(du -h "$out.1of$n" | cut -f1), from ${pins[*]};" \
  "$(wc -l < "$list") simulator data files; cells from $cells"
