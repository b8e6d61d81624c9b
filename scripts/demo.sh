#!/usr/bin/env bash
# Set up, then simulate a pallet and locate its graspable surfaces.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
VENV="${BOXLOC_VENV:-$ROOT/.venv}"
mkdir -p "$ROOT/out"
"$VENV/bin/boxloc" simulate pallet --seed 1 --out "$ROOT/out/demo.npz"
"$VENV/bin/boxloc" locate "$ROOT/out/demo.npz" --table
