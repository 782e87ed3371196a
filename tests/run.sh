#!/usr/bin/env bash
# Install everything the tests need, then run them. This is the README's test command and what CI runs.
#  - Debian's AVR toolchain and simavr when missing (apt-get; sudo when not root)
#  - torch 2.13.0 first (a CPU wheel here; unpinned torch would pull a multi-GB CUDA build)
#  - kiloforge with the learn, onnx, pettingzoo and test extras
# Extra arguments go to pytest (e.g. `bash tests/run.sh -m slow`).
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
command -v avr-gcc >/dev/null || need_apt+=(gcc-avr binutils-avr avr-libc)
[ -f /usr/lib/avr/include/avr/io.h ] || need_apt+=(avr-libc)
command -v simavr >/dev/null || need_apt+=(simavr)
[ -f /usr/include/simavr/sim_avr.h ] || need_apt+=(libsimavr-dev)
if [ ${#need_apt[@]} -gt 0 ]; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "installing ${need_apt[*]} (Debian packages for the AVR tests)"
    $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null \
        || echo "warning: could not install ${need_apt[*]}; AVR tests will skip locally (and fail in CI)"
fi

python -m pip install -q --upgrade pip >/dev/null
python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[learn,onnx,pettingzoo,test]"
python -m pytest -q "$@"
