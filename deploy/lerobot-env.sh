#!/usr/bin/env bash
# The official LeRobot in its own venv (.venv-lerobot), for the test that loads what
# `handedit export lerobot` writes; see deploy/lerobot-requirements.txt for the pins and why.
# Usage: bash deploy/lerobot-env.sh [VENV]     (default .venv-lerobot; idempotent)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv-lerobot}
PY=${PYTHON:-python3.11}

# torchcodec decodes with the system's FFmpeg libraries
need=()
for pkg in libavcodec59 libavformat59 libavutil57 libswscale6 libswresample4 libavdevice59 libavfilter8; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing Debian packages (FFmpeg libraries for torchcodec): ${need[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "import lerobot.datasets.lerobot_dataset, torchcodec.decoders" 2>/dev/null; then
  echo "LeRobot is set up in $VENV"
  exit 0
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -r deploy/lerobot-requirements.txt
"$VENV/bin/python" -m pip install -q --no-deps lerobot==0.4.4
"$VENV/bin/python" -c "import lerobot.datasets.lerobot_dataset, torchcodec.decoders"
echo "LeRobot is set up in $VENV"
