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
# Python's own bytecode cache on, whatever the machine's environment says: the suite starts ~100
# Python processes (2 workers, the serial lane, CLI and example runs, the camera and control
# processes) and with PYTHONDONTWRITEBYTECODE set (as on this project's build machines) each one
# compiled every module it imported and pytest rewrote every test module again (collection
# 8.4-12.6 s -> 4.4-5.4 s; the parallel part 348 -> 317 s in one back-to-back pair, load ~1).
# The caches are __pycache__ folders, ignored by git.
unset PYTHONDONTWRITEBYTECODE
# The compiled kernels into numba's cache before any worker needs them (setup.sh does it after an
# install; here ~1.5 s when cached, else a kernel edited since is compiled here, in one place)
bash scripts/compile_kernels.sh
.venv/bin/ruff check --quiet app tests benchmarks examples scripts
.venv/bin/lint-imports --no-cache --no-logo >/dev/null || .venv/bin/lint-imports --no-cache --no-logo
# The suite in two parts (issue 35): everything outside tests/conftest.py's serial lane on
# MONOTRACKER_TEST_WORKERS pytest-xdist workers (default 2; 0 = one process), and the serial lane
# (browser, real-clock engine, realtime tests) one test after another. Each part runs in a session
# of its own (scripts/own_session.py): with the kernel's autogroup scheduler the CPU is shared
# between sessions first, so the tests (and the app the browser tests serve) get a session's share
# beside whatever else the caller's session runs, as a deployed service and the browser do,
# instead of one thread's share among them (beside 4 busy loops started from the same shell, the
# end-to-end browser test took 53-83 s in 5 runs instead of 56-160 s: docs/performance.md "Tests
# under load"). Ctrl-C, kill and a closed terminal still stop the tests.
#
# Where the kernel has autogroups, both parts start together: the serial lane at normal weight,
# the parallel part's session at nice 19 while the serial lane runs (weight 15 against 1024:
# own_session.py --nice 19 --while PID), so it takes only the CPU the serial lane leaves idle (the
# browser tests wait on the app and the browser: ~0.6 of a core) and the serial lane keeps the
# machine as if alone; then the parallel part gets its normal weight back (beside CPU hogs it
# would get almost nothing at 19). Its workers stay in its session (MONOTRACKER_TEST_OWN_SESSION=0:
# tests/ui/conftest.py would otherwise move each worker to a new session at normal weight). The
# parallel part prints as it runs; the serial lane's output follows it. On a machine already busy
# at the start (under 60 % idle over a second), where the kernel has no autogroups, or with
# MONOTRACKER_TEST_LANES=one-after-other, the parallel part runs first, then the serial lane;
# load that comes later is own_session.py's to notice (a starved session gets its weight back).
# Extra arguments go to both parts; a part with no test selected (exit 5) is not a failure. Each
# part prints its 30 slowest tests (--durations=30), so every CI log carries the profile.
workers="${MONOTRACKER_TEST_WORKERS:-2}"
par=(-n "$workers")
[ "$workers" = "0" ] && par=()
launcher=(.venv/bin/python scripts/own_session.py)
pytest_=(.venv/bin/python -m pytest)
# the machine's idle share over one second, in % (from /proc/stat: idle + iowait over all)
idle_pct() {
  local a b
  read -r -a a < /proc/stat; sleep 1; read -r -a b < /proc/stat
  local total=$(( b[1]+b[2]+b[3]+b[4]+b[5]+b[6]+b[7]+b[8] - a[1]-a[2]-a[3]-a[4]-a[5]-a[6]-a[7]-a[8] ))
  echo $(( total > 0 ? 100 * (b[4]+b[5]-a[4]-a[5]) / total : 0 ))
}
lanes="${MONOTRACKER_TEST_LANES:-together}"
if [ "$lanes" = together ]; then
  if ! { [ "$(cat /proc/sys/kernel/sched_autogroup_enabled 2>/dev/null)" = 1 ] && [ -w /proc/self/autogroup ]; }; then
    lanes=one-after-other
  elif idle=$(idle_pct) && [ "$idle" -lt 60 ]; then
    # other load already: the parallel part at nice 19 would get almost nothing beside it
    echo "test.sh: the machine is busy (${idle} % idle): the two parts run one after the other" >&2
    lanes=one-after-other
  fi
fi
rc1=0; rc2=0
if [ "$lanes" = together ]; then
  serial_log="$(mktemp -t monotracker-serial-lane.XXXXXX)"
  trap 'rm -f "$serial_log"' EXIT
  "${launcher[@]}" "${pytest_[@]}" --lane serial --durations=30 "$@" >"$serial_log" 2>&1 &
  serial_pid=$!
  MONOTRACKER_TEST_OWN_SESSION=0 "${launcher[@]}" --nice 19 --while "$serial_pid" \
    "${pytest_[@]}" "${par[@]}" --lane parallel --durations=30 "$@" || rc1=$?
  wait "$serial_pid" || rc2=$?
  echo "--- the serial lane (it ran beside the parallel part, which ran at nice 19 meanwhile) ---"
  cat "$serial_log"
else
  "${launcher[@]}" "${pytest_[@]}" "${par[@]}" --lane parallel --durations=30 "$@" || rc1=$?
  "${launcher[@]}" "${pytest_[@]}" --lane serial --durations=30 "$@" || rc2=$?
fi
# Last, the tests marked alone (tests/conftest.py: runs_alone), with nothing else of the suite
# beside them: the end-to-end workflow holds a browser, the simulated camera and the pose stream
# to the engine's real-time limits, which on 2 cores takes the whole machine.
rc3=0
echo "--- the tests marked alone (after both parts) ---"
"${launcher[@]}" "${pytest_[@]}" --lane alone --durations=30 "$@" || rc3=$?
if [ "$rc1" = 5 ] && [ "$rc2" = 5 ] && [ "$rc3" = 5 ]; then exit 5; fi
[ "$rc1" = 5 ] && rc1=0
[ "$rc2" = 5 ] && rc2=0
[ "$rc3" = 5 ] && rc3=0
[ "$rc1" = 0 ] && [ "$rc2" = 0 ] && [ "$rc3" = 0 ] && exit 0
echo "test.sh: the parallel part exited $rc1, the serial lane $rc2, the tests marked alone $rc3" >&2
exit 1
