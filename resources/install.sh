#!/usr/bin/env bash
# Install tirdeflect and everything it needs on Debian/Ubuntu (bookworm).
#   bash resources/install.sh          # the app
#   bash resources/install.sh --test   # the app and the test tools
# System packages: Aravis (GigE Vision / USB3 Vision cameras and the fake camera
# the tests use), what PyGObject needs to build, Qt's X11 libraries, Xvfb for screenshots.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
extras="aravis"
[ "${1:-}" = "--test" ] && extras="aravis,test"

apt_packages="aravis-tools gir1.2-aravis-0.8 libaravis-0.8-0 libcairo2-dev libgirepository1.0-dev pkg-config xvfb"
# Qt's X11 (xcb) platform plugin: the live window on a desktop or under Xvfb
apt_packages="$apt_packages libxcb-icccm4 libxcb-keysyms1 libxcb-cursor0 libxcb-image0 libxcb-render-util0"
apt_packages="$apt_packages libxkbcommon-x11-0 libxcb-xkb1 libxcb-shape0 libxcb-randr0 libxcb-xinerama0 libegl1 libgl1"
missing=""
for p in $apt_packages; do
    dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "installing system packages:$missing"
        DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $missing >/dev/null
    elif command -v sudo >/dev/null && command -v apt-get >/dev/null; then
        sudo DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null
        sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $missing >/dev/null
    else
        echo "warning: cannot install$missing (not root, no apt-get); Aravis cameras will be unavailable" >&2
        extras="${extras/aravis,/}"; extras="${extras/aravis/}"
    fi
fi
python3 -m pip install -q --disable-pip-version-check -e "$here${extras:+[$extras]}"
