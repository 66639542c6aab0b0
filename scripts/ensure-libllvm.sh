#!/usr/bin/env bash
# Make sure Dr.Jit can load a libLLVM >= 16 (LLVM 15 aborts inside Dr.Jit); if none is found,
# install Debian's libllvm19. Fast when one is already there (one Python start-up).
set -euo pipefail
py=${1:-python3}

if "$py" -m ngp_mi.backend >/dev/null 2>&1; then
    exit 0
fi
echo "ensure-libllvm: no libLLVM >= 16 found; installing Debian's libllvm19" >&2
if ! command -v apt-get >/dev/null; then
    "$py" -m ngp_mi.backend || true
    echo "ensure-libllvm: no apt-get here; install LLVM >= 16 and set DRJIT_LIBLLVM_PATH" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
if ! { $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq libllvm19 >/dev/null; }; then
    if command -v nvidia-smi >/dev/null; then
        echo "ensure-libllvm: apt-get failed; continuing because a CUDA driver is present (cuda_ad_rgb needs no LLVM)" >&2
        exit 0
    fi
    echo "ensure-libllvm: 'apt-get install libllvm19' failed; install LLVM >= 16 and set DRJIT_LIBLLVM_PATH" >&2
    exit 1
fi
echo "ensure-libllvm: using $("$py" -m ngp_mi.backend)" >&2
