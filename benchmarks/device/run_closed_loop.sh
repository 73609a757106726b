#!/usr/bin/env bash
# On a lent GPU machine (the device tool, from the repository root), right after run.sh on the same warm machine:
# unpack the closed-loop bundle that benchmarks/device/bundle_closed_loop.sh built beside bundle A in /tmp/site, set
# up EGL on the NVIDIA driver, then run gpu_check's closed-loop stage within BUDGET_S seconds, its JSON and log into
# $OUT. Usage: bash benchmarks/device/run_closed_loop.sh [BUDGET_S] [gpu_check flags...]
#
# Carry .gl (EGL's loader debs) and either .whl/closed_loop.tar.xz or its parts .whl/closed_loop.tar.xz.KofN: a call
# carrying only some parts stashes them in /tmp/closed_loop/parts and stops, the call carrying the last joins and
# unpacks them and runs the stage. Once unpacked, a rerun on the still-warm machine needs nothing carried.
set -uo pipefail
budget=${1:-300}
shift || true
site=/tmp/site
cl=/tmp/closed_loop
mkdir -p "$site" "$cl/parts" "${OUT:=/tmp/out}"
t0=$(date +%s)
untar() { python3 -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='fully_trusted')" "$@"; }
# the closed-loop bundle, whole or in parts (members site/ and closed_loop/, relative to /tmp)
for part in .whl/closed_loop.tar.xz.*of*; do [ -f "$part" ] && cp "$part" "$cl/parts/"; done
if [ -f .whl/closed_loop.tar.xz ]; then
  untar .whl/closed_loop.tar.xz /tmp || { echo "run_closed_loop: cannot unpack .whl/closed_loop.tar.xz"; exit 2; }
  touch "$cl/unpacked"
elif compgen -G "$cl/parts/*of*" >/dev/null; then
  n=$(ls "$cl"/parts/ | head -1 | sed 's/.*of//')
  have=$(ls "$cl"/parts/ | wc -l)
  if [ "$have" -lt "$n" ]; then
    echo "run_closed_loop: $have of $n parts in $cl/parts; carry the others (.whl/closed_loop.tar.xz.Kof$n) in the" \
      "next call, while this machine is warm"
    exit 0
  fi
  for k in $(seq 1 "$n"); do cat "$cl/parts/closed_loop.tar.xz.${k}of$n"; done > "$cl/joined.tar.xz"
  untar "$cl/joined.tar.xz" /tmp || { echo "run_closed_loop: cannot unpack the joined parts"; exit 2; }
  rm -rf "$cl/parts" "$cl/joined.tar.xz"
  touch "$cl/unpacked"
elif [ ! -f "$cl/unpacked" ]; then
  echo "run_closed_loop: no closed-loop bundle (carry .whl/closed_loop.tar.xz or its parts .whl/closed_loop.tar.xz.KofN)"
  exit 2
fi
# bundle A (lerobot and the rest gpu_check imports), unpacked by run.sh on this warm machine, or carried here
if [ ! -d "$site/lerobot" ]; then
  [ -f .whl/bundle.tar.xz ] || { echo "run_closed_loop: $site lacks lerobot: carry .whl/bundle.tar.xz or run" \
    "benchmarks/device/run.sh first on this warm machine"; exit 2; }
  untar .whl/bundle.tar.xz "$site" || { echo "run_closed_loop: cannot unpack .whl/bundle.tar.xz"; exit 2; }
fi
# EGL through glvnd onto the NVIDIA driver (the device tool's headless-rendering notes)
if compgen -G ".gl/*.deb" >/dev/null; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  touch "$cl/gl"
elif [ ! -f "$cl/gl" ]; then
  echo "run_closed_loop: no .gl/*.deb (carry .gl: EGL's loader, apt-get download as benchmarks/device/README.md says)"
  exit 2
fi
# the cells' exports name their base policy by the absolute path they were made at: make it lead here
origin=$(cat "$cl/cells.origin")
if [ "$origin" != "$cl/cells" ] && [ ! -e "$origin" ]; then
  mkdir -p "$(dirname "$origin")" && ln -s "$cl/cells" "$origin"
fi
# hf-libero reads its paths from $LIBERO_CONFIG_PATH/config.yaml (else it prompts on stdin)
export LIBERO_CONFIG_PATH=$cl/libero-config
mkdir -p "$LIBERO_CONFIG_PATH"
benchmark=$site/libero/libero
printf '%s\n' "benchmark_root: $benchmark" "bddl_files: $benchmark/bddl_files" "init_states: $benchmark/init_files" \
  "datasets: $site/libero/datasets" "assets: $benchmark/assets" > "$LIBERO_CONFIG_PATH/config.yaml"
export PYTHONPATH="$site:$PWD" HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
# robosuite picks its EGL device by CUDA_VISIBLE_DEVICES's index, when set (a GPU UUID there would break it)
echo "run_closed_loop: unpacked in $(( $(date +%s) - t0 )) s; CUDA_VISIBLE_DEVICES=${CUDA_VISIBLE_DEVICES-unset}"
timeout 10 python3 -c "
import mujoco
from OpenGL import GL
model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><light pos=\"0 0 1\"/><geom type=\"sphere\" size=\".1\" rgba=\"1 0 0 1\"/></worldbody></mujoco>')
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
renderer = mujoco.Renderer(model, 64, 64)
renderer.update_scene(data)
frame = renderer.render()
print('run_closed_loop: EGL', GL.glGetString(GL.GL_VENDOR).decode(), '|', GL.glGetString(GL.GL_RENDERER).decode(),
      '| one 64x64 frame, mean', round(float(frame.mean()), 1))
renderer.close()
assert frame.any(), 'a blank frame'
" 2>"$OUT/egl_smoke.err" || { echo "run_closed_loop: EGL smoke failed: $(tail -1 "$OUT/egl_smoke.err")"; exit 3; }
python3 benchmarks/gpu_check.py --device cuda --budget-s "$budget" --stages 11 --closed-loop-cells "$cl/cells" \
  --scratch /tmp/gpu-check --out "$OUT/closed_loop.json" "$@" 2>&1 | tee "$OUT/closed_loop.log"
