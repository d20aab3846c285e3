#!/usr/bin/env bash
# Creates .venv (Python >= 3.11) and installs monotracker with its test extras.
# Idempotent: re-installs only when pyproject.toml changed. Used by serve.sh and test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for c in python3.11 python3.12 python3.13 python3; do
    if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
      PY="$c"; break
    fi
  done
fi
[ -n "$PY" ] || { echo "error: MonoTracker needs Python 3.11 or newer on PATH" >&2; exit 1; }
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.monotracker-installed
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setting up .venv (first run takes a minute or less)..." >&2
  # uv (Astral's installer, from PyPI) installs the same packages as pip resolves here (checked
  # with `pip freeze`) in 30-45 s instead of pip's 67-82 s on a fresh 2-core machine (empty
  # caches, downloads included): the first run of the README's commands is that much
  # shorter (issue 35). --compile-bytecode: byte-compiled as pip does (without it, on a machine
  # with PYTHONDONTWRITEBYTECODE set, every process compiled what it imported: a fresh-clone
  # CI run here took 827 s, against 714-719 s with pip earlier the same day).
  # Where uv cannot be installed or fails (no wheel for the platform, an index only pip's
  # configuration knows), pip does the install as before; MONOTRACKER_INSTALLER=pip forces pip.
  # A download cut off by the network (seen once: pip gave up on a 140 MB wheel after 6 resumes)
  # is tried again, up to 3 times, before the set-up fails.
  install() {
    if [ "${MONOTRACKER_INSTALLER:-uv}" = "uv" ] \
       && .venv/bin/python -m pip install -q --disable-pip-version-check "uv>=0.5" 2>/dev/null \
       && .venv/bin/python -m uv pip install -q --compile-bytecode --python .venv/bin/python -e ".[test]"; then
      return 0
    fi
    echo "installing with pip..." >&2
    .venv/bin/python -m pip install -q --disable-pip-version-check --retries 10 --upgrade pip \
      && .venv/bin/python -m pip install -q --disable-pip-version-check --retries 10 -e ".[test]"
  }
  tries=1
  until install; do
    if [ "$tries" -ge 3 ]; then
      echo "error: installing MonoTracker's packages failed $tries times (network?); run the command again" >&2
      exit 1
    fi
    tries=$((tries + 1))
    echo "the install failed; trying again ($tries of 3) in 10 s..." >&2
    sleep 10
  done
  echo "$want" > "$stamp"
  # the numba kernels compiled now, not at the first CT detection or camera frame (~50 CPU s
  # after an install; app/monotracker/engine/kernels.py)
  echo "compiling the kernels (half a minute)..." >&2
  bash scripts/compile_kernels.sh
fi
