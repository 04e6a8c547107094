#!/usr/bin/env bash
# Install tirdeflect with its test tools and run the whole test suite headless,
# with the Python of the virtual environment resources/install.sh made.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/resources/install.sh" --test
venv="${TIRDEFLECT_VENV:-$here/.venv}"  # where install.sh put it
case "$venv" in /*) ;; *) venv="$PWD/$venv" ;; esac
cd "$here"
export QT_QPA_PLATFORM=offscreen
exec "$venv/bin/python" -m pytest -q -p no:cacheprovider "$@"
