#!/usr/bin/env bash
# Installs RoboDojo and everything it needs into the active Python environment (use a venv).
# Usage: ./setup.sh            (from the repository root)
set -euo pipefail
cd "$(dirname "$0")"
PY="${PYTHON:-python3}"

# System libraries for headless rendering (EGL, or OSMesa) and the report test's browser, where we may install them.
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = "0" ]; then
  missing=""
  for pkg in libegl1 libegl-mesa0 libgl1 libosmesa6 chromium; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"
  done
  if [ -n "$missing" ]; then
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null
  fi
fi

"$PY" -m pip install --quiet --upgrade pip
# The real extra (piper-sdk, python-can; small, pure Python) so that the robot emulator and its tests run here too;
# the ray and sweep extras so that the launcher of several processes or machines (dojo run launcher=ray) and
# parallel sweeps (dojo run -m hydra/launcher=joblib) and their tests do; the console extra (FastAPI, Playwright's
# Python package, which drives the chromium installed above: no browser is downloaded) for the operator console;
# the warp extra (warp-lang) so that MuJoCo Warp's engine and ray tracer are tested here on Warp's CPU device.
"$PY" -m pip install --quiet -e ".[dev,real,ray,sweep,console,warp]"
# openpi-client pins numpy<2 although its websocket client runs on numpy 2: install it without its pins, and last,
# so that the protocol tests can talk to the real package. pip checks what is already installed against the
# requirements of every later install (printing a red "ERROR: ... requires numpy<2.0.0" for it), and skips that
# check with --no-deps: so nothing may be installed after it (its own dependencies, dm-tree included, are in
# the dev extra). `pip check` names this one pin; it is known and harmless.
"$PY" -m pip install --quiet --no-deps "openpi-client>=0.1.2"
echo "robodojo installed: $("$PY" -c 'import importlib.metadata as m; print(m.version("robodojo"))'); try: dojo --help"
