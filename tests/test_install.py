"""Installing tirdeflect as a lab PC needs it (resources/install.sh, the wheel).

* The install script, run from a fresh clone of this commit with the distribution's
  python3 first on PATH, in a home of its own (a new user: Debian's skeleton
  ~/.profile, ~/.local/bin on PATH): ``tirdeflect`` then works in the same shell and
  in a new login shell, lists Aravis through the distribution's python3-gi and a
  GenTL producer on GENICAM_GENTL64_PATH by its vendor, opens the live window; the
  desktop entry is valid and starts the installed program; a second run changes
  no file.
* The wheel (``pip wheel .``) holds every package and package file of the source
  tree, and the program it installs runs without the GObject bindings (no
  Aravis: Windows, macOS, a bare pip install).
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from xml.etree import ElementTree

import platformdirs
import pytest

import app
from tests.drivers.fixtures import camera_lock

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("app", "drivers", "processing")
VIKY_VENDOR = "Machine Vision Games Ltd."
DISTRO_PYTHON = Path("/usr/bin/python3")
# what pip and git need to reach their servers from this machine (certificates, proxies)
_NETWORK_ENV = ("SSL_CERT_FILE", "SSL_CERT_DIR", "REQUESTS_CA_BUNDLE", "CURL_CA_BUNDLE")


def _network_env() -> dict:
    return {k: v for k, v in os.environ.items()
            if k in _NETWORK_ENV or k.startswith(("PIP_", "UV_")) or k.lower().endswith("_proxy")}


def _fresh_checkout(dst: Path) -> Path:
    """A git clone of the commit under test (what a user gets with git clone)."""
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
    subprocess.run(["git", "clone", "-q", "--no-checkout", str(ROOT), str(dst)], check=True, timeout=120)
    subprocess.run(["git", "checkout", "-q", "--detach", head.stdout.strip()], cwd=dst, check=True, timeout=120)
    return dst


def _viky_on_its_own(tmp_path: Path) -> Path:
    """A folder holding a copy of the genicam wheel's viky.cti, as a vendor's SDK would install one."""
    from drivers.gentl import viky_cti

    cti = viky_cti()
    if cti is None:
        pytest.skip("the genicam wheel ships no viky.cti here")
    folder = tmp_path / "vendor-gentl"
    folder.mkdir()
    shutil.copy(cti, folder / "viky.cti")
    return folder


def _tree_state(*roots: Path) -> dict:
    """Every file, folder and link under ``roots``: (kind, size, mtime_ns, link target)."""
    state = {}
    for root in roots:
        paths = [root] + list(root.rglob("*")) if root.exists() or root.is_symlink() else []
        for p in paths:
            st = p.lstat()
            state[str(p)] = (st.st_mode, st.st_size, st.st_mtime_ns, os.readlink(p) if p.is_symlink() else None)
    return state


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    out = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert out.returncode == 0, f"{cmd} exited {out.returncode}\nstdout:\n{out.stdout}\nstderr:\n{out.stderr}"
    return out


@pytest.mark.slow
@pytest.mark.timeout(600)  # a cold cache downloads about 300 MB of wheels
@pytest.mark.skipif(not sys.platform.startswith("linux") or not DISTRO_PYTHON.exists()
                    or shutil.which("dpkg") is None or shutil.which("git") is None,
                    reason="the install script is for Debian/Ubuntu: needs /usr/bin/python3, dpkg and git")
def test_install_script_from_a_fresh_clone_on_the_distribution_python(tmp_path, capsys):
    clone = _fresh_checkout(tmp_path / "tirdeflect")
    home = tmp_path / "home"
    (home / ".local" / "bin").mkdir(parents=True)
    skeleton = Path("/etc/skel/.profile")
    if skeleton.exists():
        shutil.copy(skeleton, home / ".profile")
    else:  # what Debian's and Ubuntu's skeleton ~/.profile does for ~/.local/bin
        (home / ".profile").write_text('if [ -d "$HOME/.local/bin" ] ; then PATH="$HOME/.local/bin:$PATH"; fi\n')
    login_path = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"  # Debian's, /etc/profile
    env = {
        **_network_env(),
        "HOME": str(home),
        "USER": os.environ.get("USER", "root"),
        "LANG": "C.UTF-8",
        "PATH": f"{home / '.local' / 'bin'}:{login_path}",  # the distribution's python3 is the first python3
        "XDG_DATA_HOME": str(home / ".local" / "share"),
        "PIP_CACHE_DIR": os.environ.get("PIP_CACHE_DIR") or platformdirs.user_cache_dir("pip"),  # pip's own cache
        # uv's (install.sh installs the packages with it): ~/.cache/uv of the user running the tests
        "UV_CACHE_DIR": os.environ.get("UV_CACHE_DIR") or platformdirs.user_cache_dir("uv"),
    }
    first_python = _run(["bash", "-c", "command -v python3"], env=env).stdout.strip()
    assert Path(first_python).resolve() == DISTRO_PYTHON.resolve()

    # the README's first command, as written, in one shell (the GUI part: --version, no display here)
    t0 = time.monotonic()
    out = _run(["bash", "-c", "bash resources/install.sh --desktop && tirdeflect --version"], cwd=clone, env=env,
               timeout=600)
    install_s = time.monotonic() - t0
    with capsys.disabled():  # the figure shows in CI's quiet output
        print(f"\n[install.sh from a fresh clone on {DISTRO_PYTHON}: {install_s:.1f} s", end="")
    assert f"tirdeflect {app.version()}" in out.stdout.splitlines()[-1]
    # uv installed the packages (pip, the fallback, takes about a minute more)
    assert "pip installs them instead" not in out.stdout, out.stderr
    venv = clone / ".venv"
    cfg = dict(line.split(" = ", 1) for line in (venv / "pyvenv.cfg").read_text().splitlines() if " = " in line)
    assert Path(cfg["home"]) == DISTRO_PYTHON.parent, cfg
    # Aravis through the distribution's python3-gi, nothing compiled
    gi_file = _run([str(venv / "bin" / "python"), "-c", "import gi; print(gi.__file__)"]).stdout.strip()
    assert os.path.realpath(gi_file).startswith("/usr/lib/python3/dist-packages/gi/"), gi_file
    link = home / ".local" / "bin" / "tirdeflect"
    assert os.readlink(link) == str(venv / "bin" / "tirdeflect")

    # a new login shell of that user finds it and lists every camera backend
    vendor_dir = _viky_on_its_own(tmp_path)
    login_env = {"HOME": str(home), "USER": env["USER"], "LANG": "C.UTF-8", "PATH": "/usr/bin:/bin",
                 "QT_QPA_PLATFORM": "offscreen", "GENICAM_GENTL64_PATH": str(vendor_dir),
                 "TIRDEFLECT_CACHE_DIR": os.environ["TIRDEFLECT_CACHE_DIR"],
                 "TIRDEFLECT_CONFIG_DIR": os.environ["TIRDEFLECT_CONFIG_DIR"]}
    with camera_lock():  # it lists the cameras and opens the first one found: no other test's fake camera
        shell = _run(["env", "-i", *(f"{k}={v}" for k, v in login_env.items()), "bash", "-l", "-c",
                      "command -v tirdeflect && tirdeflect cameras --include-fake && tirdeflect gui --quit-after 1"],
                     cwd=tmp_path, timeout=180)
    lines = shell.stdout.splitlines()
    assert lines[0] == str(link)
    assert any(line.startswith("aravis:Fake_1 ") for line in lines), shell.stdout
    viky = [line for line in lines if line.startswith(f"gentl:{vendor_dir / 'viky.cti'}:")]
    assert len(viky) == 3 and all(VIKY_VENDOR in line for line in viky), shell.stdout
    assert lines[-1].startswith("synthetic ")

    # the menu entry is valid and starts the installed program
    entry = home / ".local" / "share" / "applications" / "tirdeflect.desktop"
    if shutil.which("desktop-file-validate"):
        _run(["desktop-file-validate", str(entry)])
    fields = dict(line.split("=", 1) for line in entry.read_text().splitlines() if "=" in line)
    assert fields["Type"] == "Application" and fields["Terminal"] == "false"
    exec_argv = shlex.split(fields["Exec"])
    assert exec_argv == [str(venv / "bin" / "tirdeflect")]
    assert _run([*exec_argv, "--version"], env=login_env).stdout.strip() == f"tirdeflect {app.version()}"
    assert ElementTree.parse(fields["Icon"]).getroot().tag == "{http://www.w3.org/2000/svg}svg"
    assert Path(fields["Icon"]).read_bytes() == (clone / "resources" / "tirdeflect.svg").read_bytes()

    # a second run checks and changes nothing
    watched = (venv, link, entry, Path(fields["Icon"]))
    before = _tree_state(*watched)
    t0 = time.monotonic()
    again = _run(["bash", "resources/install.sh", "--desktop"], cwd=clone, env=env, timeout=300)
    with capsys.disabled():
        print(f"; second run {time.monotonic() - t0:.1f} s] ", end="")
    assert "is up to date" in again.stdout, again.stdout
    assert _tree_state(*watched) == before


@pytest.mark.slow
@pytest.mark.timeout(600)  # its pip steps may each take up to 300 s (build isolation fetches setuptools)
@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to check out the commit under test")
def test_wheel_holds_every_package_and_runs_without_aravis(tmp_path):
    source = _fresh_checkout(tmp_path / "src")
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "dist"), str(source)],
         env={**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}, timeout=300)
    (wheel,) = (tmp_path / "dist").glob("tirdeflect-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        dist_info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/METADATA"))
        metadata = zf.read(f"{dist_info}/METADATA").decode()
        entry_points = zf.read(f"{dist_info}/entry_points.txt").decode()
    # every module and package file (data included) of the source tree, and nothing of tests/
    expected = {p.relative_to(source).as_posix() for pkg in PACKAGES for p in (source / pkg).rglob("*")
                if p.is_file() and "__pycache__" not in p.parts}
    assert expected - names == set()
    assert not any(n.startswith(("tests/", "resources/", "benchmarks/")) for n in names)
    assert "tirdeflect = app.cli:main" in entry_points
    requires = [line for line in metadata.splitlines() if line.startswith("Requires-Dist:")]
    gobject = [r for r in requires if "pygobject" in r.lower()]
    assert gobject and all('extra == "aravis"' in r for r in gobject), requires  # Aravis stays optional

    # the installed wheel runs where the GObject bindings cannot be imported
    site = tmp_path / "site"
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
          "--target", str(site), str(wheel)], timeout=300)
    vendor_dir = _viky_on_its_own(tmp_path)
    run_installed = (
        "import sys; sys.modules['gi'] = None; sys.path.insert(0, sys.argv.pop(1))\n"
        "import app\n"
        "assert app.__file__.startswith(sys.path[0]), app.__file__\n"
        "from app.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    env = {**os.environ, "GENICAM_GENTL64_PATH": os.pathsep.join([str(tmp_path / "no-such-sdk"), str(vendor_dir)])}
    version = _run([sys.executable, "-c", run_installed, str(site), "--version"], cwd=tmp_path, env=env)
    assert version.stdout.strip() == f"tirdeflect {app.version()}"
    cameras = _run([sys.executable, "-c", run_installed, str(site), "cameras", "--include-fake"],
                   cwd=tmp_path, env=env, timeout=120).stdout.splitlines()
    assert not any(line.startswith("aravis:") for line in cameras), cameras
    assert sum(VIKY_VENDOR in line for line in cameras) == 3, cameras
    assert cameras[-1].startswith("synthetic ")


def _link(target: Path, link: Path, *extra) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(ROOT / "resources" / "link-command.sh"), str(target), str(link), *extra],
                          capture_output=True, text=True, timeout=60)


def _fake_checkout(root: Path) -> Path:
    command = root / ".venv" / "bin" / "tirdeflect"
    command.parent.mkdir(parents=True)
    command.write_text("#!/bin/sh\necho tirdeflect\n")
    command.chmod(0o755)
    return command


def test_install_keeps_the_command_link_of_another_checkout(tmp_path):
    """Two checkouts on one PC: the second install does not take the machine-wide link from the
    first (it warns, names both and how to choose, and succeeds: CI installs from a second clone);
    --force re-points it; a link to a deleted checkout is re-pointed; a file is never replaced."""
    first, second = _fake_checkout(tmp_path / "first"), _fake_checkout(tmp_path / "second")
    link = tmp_path / "bin" / "tirdeflect"
    r = _link(first, link)
    assert r.returncode == 0 and os.readlink(link) == str(first) and r.stdout.strip() == str(link)
    r = _link(second, link)
    assert r.returncode == 0, r.stderr
    assert os.readlink(link) == str(first)  # the first checkout keeps its command
    assert r.stdout.strip() == str(second)  # the command to run for this checkout
    assert f"{link} points to {first}" in r.stderr and "--force" in r.stderr and "TIRDEFLECT_BIN_DIR" in r.stderr
    r = _link(second, link, "--force")
    assert r.returncode == 0 and os.readlink(link) == str(second) and r.stdout.strip() == str(link)
    assert _link(second, link).stderr == ""  # already ours: nothing to say
    shutil.rmtree(tmp_path / "second")  # that checkout is deleted: its link leads nowhere
    r = _link(first, link)
    assert r.returncode == 0 and os.readlink(link) == str(first) and "no longer exists" in r.stderr
    link.unlink()
    link.write_text("someone's own script\n")
    r = _link(first, link)
    assert r.returncode == 1 and "is not a link this script made" in r.stderr
    assert link.read_text() == "someone's own script\n"


def test_install_script_passes_force_to_the_link_and_documents_it():
    text = (ROOT / "resources" / "install.sh").read_text()
    assert "--force) force=--force ;;" in text
    assert 'bash "$here/resources/link-command.sh" "$target" "$link" $force' in text
    r = subprocess.run(["bash", str(ROOT / "resources" / "install.sh"), "--help"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "--force" in r.stdout


def test_install_into_a_folder_not_on_path_says_how_to_put_it_there(tmp_path):
    """TIRDEFLECT_BIN_DIR, a folder of the user's choosing that is not on PATH: the script said "open a new login
    shell, or run: export PATH=...", but no login shell adds such a folder (by-hand trial, 7 Dec 2026); it says the
    export (and where to keep it), or to run the link itself. The checkout's environment is up to date here: the
    script only checks it and makes the link."""
    bin_dir = tmp_path / "my bin"
    env = {**os.environ, "TIRDEFLECT_BIN_DIR": str(bin_dir), "PATH": "/usr/bin:/bin"}
    r = subprocess.run(["bash", "resources/install.sh", "--test"], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    link = bin_dir / "tirdeflect"
    assert os.path.islink(link) and os.path.exists(link)
    assert f'{bin_dir} is not on PATH: run export PATH="{bin_dir}:$PATH"' in r.stdout, r.stdout
    assert "~/.profile" in r.stdout and f"or run {link}" in r.stdout and "login shell" not in r.stdout, r.stdout
