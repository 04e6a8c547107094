#!/usr/bin/env bash
# Put the `tirdeflect` command on PATH: a symbolic link LINK -> TARGET (resources/install.sh).
#   bash resources/link-command.sh TARGET LINK [--force]
# TIRDEFLECT_LINK_AS=sudo runs mkdir and ln through sudo (a /usr/local/bin link as a user).
#
# A link that already points to another checkout's tirdeflect is left as it is (two
# checkouts on one PC must not take the command from each other at each install): a
# warning names both and says how to choose (--force re-points it, TIRDEFLECT_BIN_DIR=DIR
# puts this checkout's link elsewhere), and the script succeeds (an install from a second
# clone, CI's included, must not fail on it). A link whose target is gone (a deleted
# checkout) is re-pointed, with a word. A file there that is not a link is an error.
# Prints, last, the command to run: LINK when it leads to TARGET, else TARGET.
set -euo pipefail
target="$1"
link="$2"
force="${3:-}"
as="${TIRDEFLECT_LINK_AS:-}"
say() { echo "install.sh: $*" >&2; }
current="$(readlink "$link" 2>/dev/null || true)"
if [ "$current" = "$target" ]; then
    echo "$link"
    exit 0
fi
if [ -e "$link" ] && [ ! -L "$link" ]; then
    echo "install.sh: error: $link exists and is not a link this script made; remove it or set TIRDEFLECT_BIN_DIR" >&2
    exit 1
fi
if [ -L "$link" ] && [ "$force" != "--force" ]; then
    if [ -e "$link" ]; then
        echo "install.sh: warning: $link points to $current (another checkout's tirdeflect), not to" \
             "$target; left as it is so that the other checkout keeps its command. Run $target," \
             "or re-point the link with 'bash resources/install.sh --force', or link this checkout" \
             "elsewhere with TIRDEFLECT_BIN_DIR=DIR" >&2
        echo "$target"
        exit 0
    fi
    say "$link pointed to $current, which no longer exists; pointing it to $target"
fi
[ -n "$as" ] && say "linking $link with $as (~/.local/bin is not on PATH)"
$as mkdir -p "$(dirname "$link")"
$as ln -sfn "$target" "$link"
echo "$link"
