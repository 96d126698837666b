#!/usr/bin/env bash
# Idempotent setup on a fresh Debian machine: system libraries, a virtual environment in
# .venv, the project (engine + server + CLI) and the light client, both editable.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
# Mitsuba's llvm_ad_rgb variant needs LLVM 19 (the image's LLVM 15 crashes, see docs/decisions.md).
ldconfig -p | grep -q 'libLLVM.so.19' || ldconfig -p | grep -q 'libLLVM-19' || need_apt+=(libllvm19)
# PostgreSQL for the queue tests against a real server, and for multi-host deployments.
[ -x "$(ls /usr/lib/postgresql/*/bin/pg_ctl 2>/dev/null | head -n1)" ] || need_apt+=(postgresql)
# Headless Chromium and its WebDriver for the dashboard's browser tests (tests/test_dashboard_browser.py).
command -v chromium >/dev/null || need_apt+=(chromium)
command -v chromedriver >/dev/null || need_apt+=(chromium-driver)
if ((${#need_apt[@]})); then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q "${need_apt[@]}"
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
# torch is pinned to the CPU build (an unpinned torch pulls a multi-GB CUDA build).
python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[dev]" -e ./client
echo "setup: ok ($(python --version), torch $(python -c 'import torch; print(torch.__version__)'))"
