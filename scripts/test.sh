#!/usr/bin/env bash
# Set up, then run the linter and the test suite.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
VENV="${BOXLOC_VENV:-$ROOT/.venv}"
cd "$ROOT"
"$VENV/bin/ruff" check boxloc recorder replay tests
"$VENV/bin/python" -m pytest -q -n 2 --timeout=300 "$@" || exit $?
