#!/usr/bin/env bash
# Creates .venv/ in the checkout (Python >= 3.12, which lerobot 0.6.1 needs) and installs the
# project with its test extras at the versions of envs/main.lock.txt, then the overlay environments
# of envs/. Safe to run again: it only installs what is missing.
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
# The versions of envs/main.lock.txt (constraints: only what the project requires is installed).
.venv/bin/python -m pip install --quiet -c envs/main.lock.txt -e ".[test]"
# Overlay environments (envs/<name>.lock.txt other than main): a few packages put first on the path of the
# cells that need them (X-VLA: MuJoCo 3.1.6), rebuilt only when their lock changes.
for lock in envs/*.lock.txt; do
    name="$(basename "$lock" .lock.txt)"
    [ "$name" = main ] && continue
    overlay=".venv/overlays/$name"
    if ! cmp -s "$lock" "$overlay.lock.txt"; then
        rm -rf "$overlay"
        .venv/bin/python -m pip install --quiet --no-deps --target "$overlay" -r "$lock"
        cp "$lock" "$overlay.lock.txt"
    fi
done
echo "setup.sh: .venv ready ($(.venv/bin/python --version))"
