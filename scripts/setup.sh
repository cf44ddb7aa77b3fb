#!/usr/bin/env bash
# Installs everything jaxdenoise needs on a fresh Debian 12 / Python 3.11 machine:
#  1. an LLVM >= 16 for Mitsuba's LLVM variants (Debian's libllvm19; LLVM 15 crashes on some CPUs),
#     when root with apt-get; otherwise Mitsuba falls back to scalar_rgb (data_gen says so once);
#  2. the package itself, editable, with the test tools, pyoidn (the OIDN peer) and Dask (the
#     cluster extra: `--scheduler` of data_gen dataset, tested on a local cluster).
# Idempotent: a second run installs nothing new.
set -euo pipefail
cd "$(dirname "$0")/.."

have_llvm() {
  local f
  for f in /usr/lib/x86_64-linux-gnu/libLLVM-*.so* /usr/lib/llvm-*/lib/libLLVM-*.so*; do
    [[ -e "$f" && "$f" =~ libLLVM-([0-9]+) ]] && (( BASH_REMATCH[1] >= 16 )) && return 0
  done
  return 1
}

if ! have_llvm; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing libllvm19 for Mitsuba's LLVM variants"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
      || echo "setup: could not install libllvm19; Mitsuba will fall back to scalar_rgb (slow)"
  else
    echo "setup: no LLVM >= 16 found and apt-get is not usable here; Mitsuba will fall back to scalar_rgb (slow)." \
         "Install Debian's libllvm19 (or set DRJIT_LIBLLVM_PATH to a libLLVM >= 16) to fix."
  fi
fi

python -m pip install -q --disable-pip-version-check -e '.[test,oidn,cluster]'
