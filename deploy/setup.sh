#!/usr/bin/env bash
# Set up handedit on a fresh Debian machine with Python 3.11:
#   system libraries for offscreen rendering (Mesa EGL), a virtualenv in .venv, the package.
# Usage: bash deploy/setup.sh [--test]     (--test adds the test dependencies)
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
[ "${1:-}" = "--test" ] && extras="[test]"
PY=${PYTHON:-python3.11}

# Debian packages: EGL + Mesa for pyrender offscreen, venv support for the system Python, a C
# compiler for the retargeting solvers' casadi functions (handedit.retarget.compiled; without
# one they run interpreted, the same results several times slower).
need=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libgomp1 gcc libc6-dev; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
command -v "$PY" >/dev/null 2>&1 || need+=(python3.11)
"$PY" -m venv --help >/dev/null 2>&1 || need+=(python3.11-venv)
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing Debian packages: ${need[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# the tests open the QA page in headless Chromium (Debian's package); a machine that cannot
# install it still sets up, and that one test says what is missing
if [ -n "$extras" ] && ! command -v chromium >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing Debian package: chromium (for the QA page test)"
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null; } \
    || echo "warning: could not install chromium; tests/test_release.py's browser test will fail until it is installed"
fi

# the live deployment test runs its Prefect server on PostgreSQL (deploy/prefect-db.sh)
if [ -n "$extras" ] && ! ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1 && ! command -v pg_ctl >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing Debian package: postgresql (for the live deployment test's Prefect server)"
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends postgresql >/dev/null; } \
    || echo "warning: could not install postgresql; tests/test_deployments_live.py will fail until it is installed"
fi

# pip stops half-way with "No space left on device" on a full disk: say so before starting.
# .venv takes ~2 GB, ~3.5 GB with the test extras; LeRobot's venv ~6 GB more (its torch is a CUDA build).
free_mb() { df -Pm "$1" | awk 'NR==2 {print $4}'; }
need_mb=2560
[ -n "$extras" ] && need_mb=4096
if [ ! -x .venv/bin/python ] && [ "$(free_mb .)" -lt "$need_mb" ]; then
  echo "deploy/setup.sh: only $(free_mb .) MB free on $(df -P . | awk 'NR==2 {print $6}'); .venv needs about $need_mb MB." >&2
  echo "Free some space (rm -rf /tmp/pytest-of-\$USER, old runs under runs/) and run it again." >&2
  exit 1
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".${extras}"
# estimate_hands' models (Apache-2.0, ~12 MB out of a 36 MB wheel): once, into the user cache
.venv/bin/handedit models fetch \
  || echo "warning: could not fetch the hand models; videos without keypoints stop at estimate_hands until \`handedit models fetch\` succeeds"
# the test that loads an exported dataset with the official LeRobot (its own venv: its pins conflict)
if [ -n "$extras" ]; then
  [ -x .venv-lerobot/bin/python ] || [ "$(free_mb .)" -ge 7168 ] \
    || echo "warning: only $(free_mb .) MB free; LeRobot's venv needs about 7 GB and may not fit"
  bash deploy/lerobot-env.sh \
    || echo "warning: could not set up LeRobot's venv; tests/test_export_lerobot.py will fail until \`bash deploy/lerobot-env.sh\` succeeds"
fi
echo "handedit is set up in $(pwd)/.venv"
