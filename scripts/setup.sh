#!/usr/bin/env bash
# Installs what boxloc needs on a fresh Debian machine: system libraries, then a venv.
# Idempotent; sourced by demo.sh and test.sh.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${BOXLOC_VENV:-$ROOT/.venv}"

# open3d needs libusb and OpenGL/OpenMP runtimes; the headless Rerun viewer needs Vulkan.
DEB_PKGS="libusb-1.0-0 libgl1 libgomp1 libvulkan1 mesa-vulkan-drivers"
# Optional: a C compiler and Python's headers compile the kernels ahead of time (below).
DEB_OPTIONAL="gcc python3-dev"
missing=""
for p in $DEB_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ "$(id -u)" = 0 ]; then
  # as root (CI, a fresh machine): always update and install; a no-op when present
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null
  apt-get install -y -qq $DEB_PKGS $DEB_OPTIONAL >/dev/null
elif [ -n "$missing" ]; then
  echo "setup: missing Debian packages:$missing" >&2
  echo "setup: run as root: apt-get update && apt-get install -y$missing" >&2
  exit 2
fi

if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
"$VENV/bin/python" -m pip install -q -e "$ROOT[test]"
# Byte-compile boxloc's own modules, as pip does for an installed wheel: an editable install
# otherwise compiles each of them from source at every start where bytecode may not be
# written (PYTHONDONTWRITEBYTECODE, a read-only checkout): 0.3 s of every `boxloc locate`.
"$VENV/bin/python" -m compileall -q "$ROOT/boxloc" "$ROOT/recorder" "$ROOT/replay" >/dev/null
# Compile the numba kernels now (about 11 s), into numba's cache beside the sources, or under
# NUMBA_CACHE_DIR when set (set it the same way for boxloc then): the first scan after set-up
# is as fast as the second. A no-op, bar 2 s, while the cache matches the sources.
"$VENV/bin/python" "$ROOT/scripts/warm_up.py"
# Compile them ahead of time too, into boxloc/_kernels_aot*.so (about 2 min, with gcc and
# Python's headers; checked against the JIT, products identical): `boxloc locate`, one scan,
# then loads no numba (1.5 s less). Optional: without a compiler boxloc keeps the JIT.
# A no-op while the module matches the sources.
"$VENV/bin/python" "$ROOT/scripts/build_kernels.py" --if-stale \
  || echo "setup: kernels not compiled ahead of time; boxloc uses numba's JIT" >&2
