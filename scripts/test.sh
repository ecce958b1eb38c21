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
# The whole suite in one run, three test processes (pytest-xdist) on the two cores: the
# topic tests wait on the clock part of the time, and the third process uses what they leave.
# Each process has its own ROS domain. A file runs in one process (--dist loadfile: its
# module fixtures are built once), and files holding a `slow` test start first (conftest.py;
# --no-loadscope-reorder keeps that order). Every test must pass on such a loaded machine:
# live graphs are checked for what they count as lost, not for spare CPU.
echo "== pytest (three processes)"
run_pytest -n 3 --dist loadfile --no-loadscope-reorder
