#!/usr/bin/env bash
# The tests open the demo page in a real headless browser: make sure Debian's chromium is there.
# Fast when it is (one `command -v`).
set -euo pipefail
for name in chromium chromium-browser google-chrome; do
    if command -v "$name" >/dev/null; then exit 0; fi
done
echo "ensure-chromium: no chromium found; installing Debian's chromium" >&2
if ! command -v apt-get >/dev/null; then
    echo "ensure-chromium: no apt-get here; install chromium (or google-chrome) for the browser tests" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends chromium >/dev/null
echo "ensure-chromium: $(chromium --version)" >&2
