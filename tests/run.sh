#!/usr/bin/env bash
# Set up the test environment, then run the tests. This is the README's test command and what CI runs.
# The tests get their own virtual environment, .venv-test in the repository root (git-ignored; delete it
# to start afresh), so the Python you run this with is left as it is:
#  - Debian's AVR toolchain and simavr when missing (apt-get; sudo when not root), said before it runs
#  - in .venv-test: torch 2.13.0 first, the CPU build from PyTorch's CPU index when it is reachable
#    (PyPI's Linux wheel is the CUDA build: several GB of nvidia-* packages; without the index pip says
#    so and falls back to it, or to a local wheel), then kiloforge (editable) with the extras the tests
#    use; skipped while pyproject.toml and this script are unchanged since the last set-up. The learn
#    extra's torch bound in pyproject.toml ends below the next minor (tests/test_install_pins.py)
# Environment: PYTHON (default python3) creates the venv; TEST_VENV moves it; TORCH_INDEX_URL replaces the
# CPU index (empty: PyPI only).
# Extra arguments go to pytest (e.g. `bash tests/run.sh -m slow`).
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH="torch==2.13.0"
TORCH_INDEX_URL="${TORCH_INDEX_URL-https://download.pytorch.org/whl/cpu}"
EXTRAS="learn,onnx,pettingzoo,sweep,fast,test"  # sweep: the Ray Tune tests; fast: Numba, so the compiled simulator code is tested
VENV="${TEST_VENV:-.venv-test}"

need_apt=()
command -v avr-gcc >/dev/null || need_apt+=(gcc-avr binutils-avr avr-libc)
[ -f /usr/lib/avr/include/avr/io.h ] || need_apt+=(avr-libc)
command -v simavr >/dev/null || need_apt+=(simavr)
[ -f /usr/include/simavr/sim_avr.h ] || need_apt+=(libsimavr-dev)
if [ ${#need_apt[@]} -gt 0 ]; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    echo "tests/run.sh: installing Debian packages ${need_apt[*]} with ${SUDO:-root} apt-get" \
         "(the AVR build and simavr tests need them; without them they skip locally and fail in CI)"
    $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null \
        || echo "tests/run.sh: warning: could not install ${need_apt[*]}; AVR tests will skip locally (and fail in CI)"
fi

stamp="$VENV/.kiloforge-test-setup"
want="$TORCH .[$EXTRAS] $(cat pyproject.toml tests/run.sh | sha256sum | cut -c1-16)"
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "tests/run.sh: installing $TORCH and kiloforge[$EXTRAS] (editable) into $VENV, a venv of its own" \
         "(your Python is not changed)"
    [ -x "$VENV/bin/python" ] || "${PYTHON:-python3}" -m venv "$VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
    "$VENV/bin/python" -m pip install -q "$TORCH" ${TORCH_INDEX_URL:+--extra-index-url "$TORCH_INDEX_URL"}
    "$VENV/bin/python" -m pip install -q -e ".[$EXTRAS]"
    echo "$want" >"$stamp"
fi
"$VENV/bin/python" -m pytest -q "$@"
