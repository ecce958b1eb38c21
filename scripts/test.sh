#!/usr/bin/env bash
# Set everything up (scripts/bootstrap.sh), then lint (ruff), type-check (mypy) and run the
# whole test suite (pytest). Extra arguments go to pytest instead, as one run, e.g.
# `scripts/test.sh -m "not slow"` or `scripts/test.sh tests/test_em_sam_topics.py`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh" --test
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

echo "== ruff"
ruff check .
ruff format --check .
echo "== mypy"
mypy
# pytest exit status 5 (no tests collected) is a failure: a suite that finds nothing passed
# nothing.
run_pytest() {
  set +e
  python -m pytest "$@"
  local status=$?
  set -e
  if [[ $status == 5 ]]; then
    echo "test.sh: error: pytest collected no tests ($*); that is a failure" >&2
    return 1
  fi
  return $status
}

if [[ $# -gt 0 ]]; then
  echo "== pytest $*"
  run_pytest "$@"
  exit $?
fi
# The whole suite in two parts. First the tests that run no ROS graph against the clock
# (units, processors, offline replays: no `topic` mark), two at a time (pytest-xdist, a
# worker per core; each worker has its own ROS domain). Then the topic tests, one at a time:
# live graphs that must keep up get both cores, as a user's machine would give them.
echo "== pytest: tests without a ROS graph (two workers)"
status=0
run_pytest -m "not topic" -n 2 || status=1
echo "== pytest: topic tests (one at a time)"
run_pytest -m topic || status=1
exit $status
