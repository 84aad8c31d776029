#!/usr/bin/env bash
# Sets up everything Sim2Act needs on a fresh Debian machine: the system libraries for
# offscreen MuJoCo rendering (Mesa EGL), Chromium (the dashboard's tests drive it headless),
# PostgreSQL (the servers' databases beyond one machine; the tests start a throw-away cluster of their
# own on a free loopback port, whether or not Debian's package runs its main cluster on 5432) and a
# virtual environment with the pinned packages.
# Idempotent: `make` calls it only when pyproject.toml or this script changed since the last setup.
set -euo pipefail
venv="${1:-.venv}"

system_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 chromium postgresql)
# Debian's python3 makes venvs only with python3-venv (ensurepip); a Python built elsewhere brings its own
if ! python3.11 -c 'import ensurepip' 2>/dev/null && ! python3 -c 'import ensurepip' 2>/dev/null; then
    system_packages+=(python3-venv)
fi
missing=()
for pkg in "${system_packages[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    if [ "$(id -u)" -ne 0 ]; then
        echo "sim2act setup: missing system packages ${missing[*]}; run: sudo apt-get update && sudo apt-get install -y ${missing[*]}" >&2
        exit 1
    fi
    echo "sim2act setup: installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"
fi

[ -x "$venv/bin/python" ] || python3.11 -m venv "$venv" 2>/dev/null || python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
# torch first and pinned: with torch 2.13.0 already satisfied nothing pulls a CUDA build.
"$venv/bin/python" -m pip install -q "torch==2.13.0"
"$venv/bin/python" -m pip install -q -e ".[test]"
echo "sim2act setup: ready ($venv)"
