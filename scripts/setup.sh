#!/usr/bin/env bash
# Install everything roadgonio needs on a fresh Debian/Ubuntu machine (run as root or with sudo):
# libLLVM >= 16 for Dr.Jit's CPU backend, then the package itself with its test tools.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi

have_llvm16() {
  local f v
  for f in /usr/lib/x86_64-linux-gnu/libLLVM*.so* /usr/lib/aarch64-linux-gnu/libLLVM*.so*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -nE 's/^libLLVM-?([0-9]+).*/\1/p; s/^libLLVM\.so\.([0-9]+).*/\1/p' | head -n 1)
    if [ -n "$v" ] && [ "$v" -ge 16 ]; then return 0; fi
  done
  return 1
}
if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] || have_llvm16; then
  echo "setup: libLLVM >= 16 present"
elif command -v apt-get >/dev/null 2>&1; then
  echo "setup: installing libLLVM 19 (Dr.Jit's CPU backend needs LLVM >= 16)"
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
else
  echo "setup: no apt-get; install libLLVM >= 16 yourself or set DRJIT_LIBLLVM_PATH" >&2
fi
PY="${PYTHON:-python3}"
"$PY" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
LOG="${TMPDIR:-/tmp}/roadgonio-setup-pip.log"
if ! "$PY" -m pip install -q -e ".[test]" >"$LOG" 2>&1; then
  cat "$LOG" >&2
  echo "setup: pip install failed (log above, also in $LOG)" >&2
  exit 1
fi
echo "setup: roadgonio installed ($("$PY" -c 'import roadgonio; print(roadgonio.__version__)'))"
