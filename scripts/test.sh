#!/usr/bin/env bash
# Installs what the tests need, checks the house rules (ruff, the import contracts: see
# CONTRIBUTING.md), then runs the whole suite (2 workers, see below). Extra arguments go to pytest.
# The web app's end-to-end tests drive Debian's chromium (never a downloaded browser).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${MONOTRACKER_CHROMIUM:-}" ] && ! [ -x /usr/bin/chromium ] && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing Debian's chromium for the browser tests..." >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
  else
    echo "error: the browser tests need chromium: run 'sudo apt-get install -y chromium' (Debian/Ubuntu)" \
         "or set MONOTRACKER_CHROMIUM to a Chromium binary" >&2
    exit 1
  fi
fi
bash scripts/setup.sh
.venv/bin/ruff check --quiet app tests benchmarks examples scripts
.venv/bin/lint-imports --no-cache --no-logo >/dev/null || .venv/bin/lint-imports --no-cache --no-logo
# Two pytest-xdist workers (MONOTRACKER_TEST_WORKERS: another count, 0 = one process): the tests in
# tests/conftest.py's serial lane (browser, real-clock engine, realtime) run one after another on
# one worker while the other worker runs the rest (issue 35). Arguments after ours win (-n 0).
workers="${MONOTRACKER_TEST_WORKERS:-2}"
if [ "$workers" = "0" ]; then
  exec .venv/bin/python -m pytest "$@"
fi
exec .venv/bin/python -m pytest -n "$workers" --dist loadgroup "$@"
