#!/usr/bin/env bash
# Create the virtualenv and install ManiEval with its pinned dependencies (constraints.txt):
# install-python.sh [VENV] [EXTRAS], EXTRAS `dev` (the default: the tests' and linters' tools)
# or empty (ManiEval alone, what `manieval evaluate` needs).
set -euo pipefail
venv=${1:-.venv}
extras=${2-dev}
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
pip_install() {
  if ! "$venv/bin/python" -m pip install -q "$@" >"$log" 2>&1; then
    # This machine's pip config names local indexes that may not exist: drop that noise.
    grep -v '^WARNING: Location' "$log" >&2
    echo "pip install $* failed" >&2
    exit 1
  fi
}
pip_install --upgrade pip
pip_install -c constraints.txt -e evaluator/sdk -e ".${extras:+[$extras]}"
