#!/usr/bin/env bash
# Install tirdeflect on Debian/Ubuntu into a virtual environment of its own.
#   bash resources/install.sh             # the app
#   bash resources/install.sh --test      # the app and the test tools
#   bash resources/install.sh --desktop   # the app and a menu entry with its icon
#   bash resources/install.sh --force     # re-point a `tirdeflect` link of another checkout
#
# Where things go:
#   virtual environment   <this checkout>/.venv (TIRDEFLECT_VENV=DIR overrides); pip
#                         installs the checkout editable, so `git pull` updates the app
#   `tirdeflect` command  a symbolic link to .venv/bin/tirdeflect in ~/.local/bin when
#                         that directory is on PATH, else in /usr/local/bin (as root or
#                         with sudo); TIRDEFLECT_BIN_DIR=DIR overrides. A link there that
#                         points to another checkout is kept (a warning says so): --force
#                         re-points it to this one
#   menu entry, icon      (--desktop) ~/.local/share/applications, ~/.local/share/icons;
#                         as root /usr/local/share/applications, /usr/local/share/icons
#                         (for every user); XDG_DATA_HOME=DIR overrides
# Python: the distribution's /usr/bin/python3 (>= 3.10): pip never touches it (PEP 668)
# and its python3-gi gives the Aravis bindings without compiling PyGObject.
# TIRDEFLECT_PYTHON=/path/to/python3 picks another interpreter (pyenv, conda: then
# PyGObject is compiled, with the -dev packages below).
# System packages (apt-get, as root or with sudo): python3-venv, python3-gi, Aravis and
# its tools (GigE Vision / USB3 Vision cameras, the fake camera the tests use), Qt's X11
# libraries, Xvfb. A second run checks everything and changes nothing.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
want_test=0
want_desktop=0
force=""
for arg in "$@"; do
    case "$arg" in
        --test) want_test=1 ;;
        --desktop) want_desktop=1 ;;
        --force) force=--force ;;
        -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "${BASH_SOURCE[0]}"; exit 0 ;;
        *) echo "install.sh: unknown option '$arg'; use --test, --desktop, --force or --help" >&2; exit 2 ;;
    esac
done
say() { echo "install.sh: $*"; }
die() { echo "install.sh: error: $*" >&2; exit 1; }
is_root() { [ "$(id -u)" = 0 ]; }
if is_root && [ -n "${SUDO_USER:-}" ] && [ "$(stat -c %U "$here")" != root ]; then
    echo "install.sh: warning: run as root through sudo, the environment in $here will belong to root;" \
         "run 'bash resources/install.sh' as $SUDO_USER instead (it calls sudo where it must)" >&2
fi

# ---------------------------------------------------------------- the interpreter
py_ok() {  # python >= 3.10 that runs
    "$1" -c 'import sys; sys.exit(sys.version_info < (3, 10))' >/dev/null 2>&1
}
if [ -n "${TIRDEFLECT_PYTHON:-}" ]; then
    py="$TIRDEFLECT_PYTHON"
    py_ok "$py" || die "TIRDEFLECT_PYTHON=$py does not run or is older than Python 3.10"
elif py_ok /usr/bin/python3; then
    py=/usr/bin/python3
elif command -v python3 >/dev/null && py_ok "$(command -v python3)"; then
    py="$(command -v python3)"
else
    die "tirdeflect needs Python >= 3.10 (Debian 12, Ubuntu 22.04 or newer); set TIRDEFLECT_PYTHON=/path/to/python3"
fi
py_version="$("$py" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
# the distribution's own Python (from a Debian package) takes python3-gi and python3-venv
distro_py=0
if command -v dpkg >/dev/null && dpkg -S "$(readlink -f "$py")" >/dev/null 2>&1; then
    distro_py=1
fi

# ---------------------------------------------------------------- system packages
apt_packages="aravis-tools gir1.2-aravis-0.8 libaravis-0.8-0 xvfb"
if [ "$distro_py" = 1 ]; then
    apt_packages="$apt_packages python3-venv python${py_version}-venv python3-gi"
else  # PyGObject is compiled for this interpreter
    apt_packages="$apt_packages libcairo2-dev libgirepository1.0-dev pkg-config"
fi
# Qt's X11 (xcb) platform plugin: the live window on a desktop or under Xvfb
apt_packages="$apt_packages libxcb-icccm4 libxcb-keysyms1 libxcb-cursor0 libxcb-image0 libxcb-render-util0"
apt_packages="$apt_packages libxkbcommon-x11-0 libxcb-xkb1 libxcb-shape0 libxcb-randr0 libxcb-xinerama0 libegl1 libgl1"
[ "$want_test" = 1 ] && apt_packages="$apt_packages git desktop-file-utils"
missing=""
if command -v dpkg >/dev/null; then
    for p in $apt_packages; do  # removed packages keep "config-files": only "installed" counts
        [ "$(dpkg-query -W -f='${db:Status-Status}' "$p" 2>/dev/null)" = installed ] || missing="$missing $p"
    done
fi
if [ -n "$missing" ]; then
    apt=""
    if is_root && command -v apt-get >/dev/null; then
        apt="env"
    elif command -v sudo >/dev/null && command -v apt-get >/dev/null; then
        apt="sudo"
    fi
    if [ -n "$apt" ]; then
        say "installing system packages:$missing"
        $apt DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null
        # shellcheck disable=SC2086
        $apt DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $missing >/dev/null
    else
        echo "install.sh: warning: cannot install$missing (not root, no sudo or no apt-get);" \
             "Aravis cameras may be unavailable" >&2
    fi
fi

# ---------------------------------------------------------------- the virtual environment
venv="${TIRDEFLECT_VENV:-$here/.venv}"
case "$venv" in /*) ;; *) venv="$PWD/$venv" ;; esac
base_of() {  # the installation a python (or a venv's python) belongs to, and its version
    "$1" -c 'import sys; print(sys.base_prefix, "%d.%d" % sys.version_info[:2])' 2>/dev/null || true
}
if [ -e "$venv" ] && [ "$(base_of "$venv/bin/python")" != "$(base_of "$py")" ]; then
    [ -f "$venv/pyvenv.cfg" ] || die "$venv exists and is not a virtual environment; move it or set TIRDEFLECT_VENV"
    say "$venv was made with another Python; making it again with $py"
    rm -rf "$venv"
fi
if [ ! -x "$venv/bin/python" ]; then
    say "making the virtual environment $venv (Python $py_version: $py)"
    "$py" -m venv "$venv" || die "'$py -m venv' failed: install python${py_version}-venv (apt-get install python3-venv) or set TIRDEFLECT_PYTHON"
fi
vpy="$venv/bin/python"
site="$("$vpy" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"

# Aravis' GObject bindings: the base interpreter's gi (Debian: python3-gi), made visible
# in the venv alone (a .pth naming a folder that holds only a link to gi), so nothing
# else of the distribution's Python leaks in; else PyGObject from pip (the aravis extra).
extras="formats"  # Photron MRAW and Phantom CINE readers (docs/inputs.md)
gi_dir="$("$py" -s -c 'import gi, os; print(os.path.dirname(gi.__file__))' 2>/dev/null || true)"
if [ -n "$gi_dir" ]; then
    mkdir -p "$venv/distro-gi"
    [ "$(readlink "$venv/distro-gi/gi" 2>/dev/null)" = "$gi_dir" ] || ln -sfn "$gi_dir" "$venv/distro-gi/gi"
    pth="$site/tirdeflect-distro-gi.pth"
    [ "$(cat "$pth" 2>/dev/null)" = "$venv/distro-gi" ] || echo "$venv/distro-gi" >"$pth"
elif pkg-config --exists gobject-introspection-1.0 cairo 2>/dev/null; then
    extras="$extras,aravis"
fi
[ "$want_test" = 1 ] && extras="${extras:+$extras,}test"

# pip runs only when something changed: the stamp records what the venv holds
stamp="$venv/.tirdeflect-install"
key="python=$(base_of "$py") checkout=$here pyproject=$(sha256sum "$here/pyproject.toml" | cut -d' ' -f1)"
old_key="$(sed -n 1p "$stamp" 2>/dev/null || true)"
old_extras="$(sed -n 2p "$stamp" 2>/dev/null || true)"
need_pip=0
[ "$key" = "$old_key" ] || need_pip=1
for e in ${extras//,/ }; do
    case ",$old_extras," in *",$e,"*) ;; *) need_pip=1 ;; esac
done
if [ "$need_pip" = 0 ] && ! "$venv/bin/tirdeflect" --version >/dev/null 2>&1; then
    need_pip=1
fi
if [ "$need_pip" = 1 ]; then
    [ "$key" = "$old_key" ] && [ -n "$old_extras" ] && extras="$old_extras${extras:+,$extras}"
    extras="$(echo "$extras" | tr ',' '\n' | sed '/^$/d' | sort -u | paste -sd, -)"
    say "installing tirdeflect${extras:+[$extras]} and its Python packages into $venv"
    # uv (a pip-compatible installer, itself one wheel from PyPI) installs the packages: pip
    # unpacks the environment's ~1.3 GB of wheels one after the other, about 40 s of CPU on a
    # 2-core PC (51 s in all, its cache warm), uv in parallel (25 s in all with the uv wheel,
    # its cache cold; 18 s warm). pip does it where uv cannot: no uv wheel for this machine, or
    # an index that only pip's configuration names (uv does not read pip.conf). uv takes the
    # system's certificates (a lab network that inspects TLS installs its own there):
    # UV_SYSTEM_CERTS, and UV_NATIVE_TLS, its older name.
    # Neither byte-compiles (pip's --no-compile): compiling all ~6800 modules of the environment
    # was half pip's CPU time (29 of 58 s on a 2-core PC); Python compiles a module the first
    # time it imports one instead (the venv is the user's, so the cache is written there once),
    # and most are never imported ...
    uv_log="$(mktemp "${TMPDIR:-/tmp}/tirdeflect-uv.XXXXXX")"
    if PIP_USER=0 "$vpy" -m pip install -q --disable-pip-version-check --no-compile uv >"$uv_log" 2>&1 &&
        UV_SYSTEM_CERTS="${UV_SYSTEM_CERTS:-1}" UV_NATIVE_TLS="${UV_NATIVE_TLS:-1}" \
            "$venv/bin/uv" pip install -q --python "$vpy" -e "$here${extras:+[$extras]}" >"$uv_log" 2>&1; then
        :
    else
        sed 's/^/  /' "$uv_log" >&2
        say "uv could not install the packages (above); pip installs them instead (about a minute)"
        PIP_USER=0 "$vpy" -m pip install -q --disable-pip-version-check --no-compile -e "$here${extras:+[$extras]}"
    fi
    rm -f "$uv_log"
    # ... except where PYTHONDONTWRITEBYTECODE is set (this project's machines set it): there every
    # process would compile what it imports again, each start of the window and of its reconstruction
    # process. The modules the app imports are compiled once here instead (a few seconds), and
    # app.worker_preload's warm-up compiles the reconstruction's Numba kernels into the checkout's
    # __pycache__ (15-60 s on a 2-core PC, 56 s measured beside other work; once: else the first frames
    # of the first run pay it).
    say "compiling the app and its reconstruction kernels ahead, once (up to about a minute on 2 cores)"
    env -u PYTHONDONTWRITEBYTECODE "$vpy" -c 'import app.gui.window, app.cli.process, app.batch.parallel
import processing.reconstruct, processing.chain_image, processing.dic_kernels, app.worker_preload' >/dev/null 2>&1 ||
        say "could not import the app to compile it ahead (it compiles as it runs)"
    printf '%s\n%s\n' "$key" "$extras" >"$stamp"
else
    say "$venv is up to date"
fi
version="$("$venv/bin/tirdeflect" --version)" || die "$venv/bin/tirdeflect does not run"
if ! "$vpy" -c 'import gi; gi.require_version("Aravis", "0.8")' >/dev/null 2>&1; then
    echo "install.sh: warning: no Aravis 0.8 GObject bindings in $venv: aravis: cameras are unavailable" \
         "(GenTL producers and the synthetic camera work); install python3-gi and gir1.2-aravis-0.8" >&2
fi

# ---------------------------------------------------------------- `tirdeflect` on PATH
on_path() { case ":$PATH:" in *":$1:"*) return 0 ;; esac; return 1; }
as=""
if [ -n "${TIRDEFLECT_BIN_DIR:-}" ]; then
    bin="$TIRDEFLECT_BIN_DIR"
elif on_path "$HOME/.local/bin"; then
    bin="$HOME/.local/bin"
elif is_root || [ -w /usr/local/bin ]; then
    bin=/usr/local/bin
elif command -v sudo >/dev/null; then
    bin=/usr/local/bin
    as=sudo
else
    bin="$HOME/.local/bin"
fi
link="$bin/tirdeflect"
target="$venv/bin/tirdeflect"
command_is="$(TIRDEFLECT_LINK_AS="$as" bash "$here/resources/link-command.sh" "$target" "$link" $force)" || exit 1
if [ "$command_is" = "$link" ]; then
    say "$version: $link -> $target"
else
    say "$version: $target (the command on PATH stays the other checkout's)"
fi
found="$(command -v tirdeflect || true)"
if [ "$command_is" != "$link" ]; then
    :
elif ! on_path "$bin" && [ "$bin" = "$HOME/.local/bin" ]; then  # a login shell's profile adds it when it exists
    say "$bin is not on PATH yet: open a new login shell, or run: export PATH=\"$bin:\$PATH\""
elif ! on_path "$bin"; then  # a folder of the user's choosing: no profile adds it
    say "$bin is not on PATH: run export PATH=\"$bin:\$PATH\" (and add that line to ~/.profile to keep it), or run $link"
elif [ -n "$found" ] && [ "$found" != "$link" ]; then
    echo "install.sh: warning: 'tirdeflect' on PATH is $found, which comes before $link;" \
         "run $link or remove the other one" >&2
fi

# ---------------------------------------------------------------- menu entry (--desktop)
if [ "$want_desktop" = 1 ]; then
    if [ -n "${XDG_DATA_HOME:-}" ]; then share="$XDG_DATA_HOME"
    elif is_root; then share=/usr/local/share
    else share="$HOME/.local/share"; fi
    icon="$share/icons/hicolor/scalable/apps/tirdeflect.svg"
    entry="$share/applications/tirdeflect.desktop"
    mkdir -p "$(dirname "$icon")" "$(dirname "$entry")"
    cmp -s "$here/resources/tirdeflect.svg" "$icon" || cp "$here/resources/tirdeflect.svg" "$icon"
    new_entry="$(mktemp)"
    trap 'rm -f "$new_entry"' EXIT
    cat >"$new_entry" <<EOF
[Desktop Entry]
Type=Application
Version=1.0
Name=tirdeflect
GenericName=TIR deflectometry
Comment=Live water-surface height maps from a camera (total-internal-reflection deflectometry)
Exec="$target"
Icon=$icon
Terminal=false
Categories=Science;Physics;
Keywords=deflectometry;schlieren;water;surface;camera;GenICam;
EOF
    if ! cmp -s "$new_entry" "$entry"; then
        cp "$new_entry" "$entry"
        chmod 644 "$entry"
    fi
    say "menu entry: $entry"
fi
