#!/usr/bin/env bash
# Set-up and everyday tasks. On a fresh machine:
#   ./dev.sh demo    install into .venv, then run the end-to-end demo (`cdrb quickstart`)
#   ./dev.sh test    install into .venv, then run the test suite (what CI runs)
set -euo pipefail
cd "$(dirname "$0")"
VENV=${CDRB_VENV:-.venv}

setup() {
  if [ ! -x "$VENV/bin/python" ]; then
    python3 -m venv "$VENV"
  fi
  # torch first, pinned: 2.13.0 is a local CPU build here; a bare `torch` requirement would pull CUDA wheels.
  "$VENV/bin/python" -m pip install -q torch==2.13.0
  # the tests also run `cdrb grid` on a local Ray instance, Minari round trips and TensorBoard logs: the optional
  # [ray], [minari] and [tensorboard] extras are part of the dev set-up
  "$VENV/bin/python" -m pip install -q -e ".[dev,ray,minari,tensorboard]"
}

case "${1:-}" in
  setup) setup ;;
  cdrb)  shift; exec "$VENV/bin/cdrb" "$@" ;;  # the installed command, without activating .venv
  demo)  setup; shift; "$VENV/bin/cdrb" quickstart "$@" ;;
  # one pytest-xdist worker per core (tests/conftest.py gives each one torch thread); an idle worker takes queued
  # tests from the other (worksteal); CDRB_TEST_WORKERS=0 runs serially
  test)  setup; shift; "$VENV/bin/python" -m pytest -q -n "${CDRB_TEST_WORKERS:-auto}" --dist worksteal "$@" ;;
  *) echo "usage: ./dev.sh {setup|demo|test|cdrb} [args...]" >&2; exit 2 ;;
esac
