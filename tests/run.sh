#!/usr/bin/env bash
# Install tirdeflect with its test tools and run the whole test suite headless.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/resources/install.sh" --test
cd "$here"
export QT_QPA_PLATFORM=offscreen
exec python3 -m pytest -q -p no:cacheprovider "$@"
