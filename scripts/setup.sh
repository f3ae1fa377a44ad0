#!/usr/bin/env bash
# Creates .venv/ in the checkout (Python >= 3.12, which lerobot 0.6.1 needs) and installs the
# project with its test extras. Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

find_python() {
    for candidate in "${VQB_PYTHON:-}" python3.12 /root/.pyenv/versions/3.12.1/bin/python3.12 python3.13 python3; do
        [ -n "$candidate" ] || continue
        if command -v "$candidate" >/dev/null 2>&1 &&
            "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
            command -v "$candidate"
            return 0
        fi
    done
    echo "setup.sh: no Python >= 3.12 found; set VQB_PYTHON to one" >&2
    return 1
}

if [ ! -x .venv/bin/python ]; then
    "$(find_python)" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test]"
echo "setup.sh: .venv ready ($(.venv/bin/python --version))"
