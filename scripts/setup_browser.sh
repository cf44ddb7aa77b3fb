#!/usr/bin/env bash
# Installs headless Chromium for the viewer's browser test (tests/test_viewer.py, marked slow):
# Debian's `chromium` package when root with apt-get. Not part of scripts/setup.sh: the default test
# run does not pay for the browser. Idempotent.
set -euo pipefail
if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "setup_browser: installing Debian's chromium (headless browser for the viewer test)"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) || {
    echo "setup_browser: could not install chromium"; exit 1; }
else
  echo "setup_browser: not root or no apt-get: install Chromium by hand to run the viewer's browser test"
  exit 1
fi
