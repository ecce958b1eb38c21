#!/usr/bin/env bash
# Set everything up (scripts/bootstrap.sh), then lint (ruff), type-check (mypy) and run the
# whole test suite (pytest). Extra arguments go to pytest, e.g. `scripts/test.sh -m "not slow"`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/bootstrap.sh"
# shellcheck source=scripts/env.sh
source "$ROOT/scripts/env.sh"
cd "$ROOT"

echo "== ruff"
ruff check .
ruff format --check .
echo "== mypy"
mypy
echo "== pytest"
set +e
python -m pytest "$@"
status=$?
set -e
if [[ $status == 5 ]]; then
  echo "test.sh: error: pytest collected no tests; that is a failure" >&2
  exit 1
fi
exit $status
