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
# Python writes each module's bytecode once, and every later process reads it. PYTHONDONTWRITEBYTECODE
# (set in the environment of this project's machines) together with pip's --no-compile (resources/install.sh) made
# every one of the suite's several hundred Python processes (each CLI run, batch worker and window's
# reconstruction process) compile numpy, SciPy, Numba ... from source: a 4-frame `tirdeflect process`
# took 4.7 s instead of 2.2 s. Only the modules that run get compiled, by the first process that needs them.
unset PYTHONDONTWRITEBYTECODE
# A test stuck past its limit, even one holding the GIL, ends pytest with every
# thread's stack (tests/conftest.py, "a stuck test ends the run"); its name is in this file.
# With pytest-xdist each worker keeps its own note: this file's name with .gw0, .gw1, ...
note=$(mktemp "${TMPDIR:-/tmp}/tirdeflect-watchdog.XXXXXX")
export TIRDEFLECT_WATCHDOG_NOTE="$note"
# The tests run in parallel, one pytest-xdist worker per core (at most 4; TIRDEFLECT_TEST_WORKERS=N
# sets it, 1 runs them in this one process). The tests that share the machine's cameras take a
# lock and run one at a time (tests/conftest.py, "one test at a time: the cameras").
workers="${TIRDEFLECT_TEST_WORKERS:-$(nproc 2>/dev/null || echo 1)}"
[ "$workers" -le 4 ] || workers=4
parallel=()
if [ "$workers" -gt 1 ] && "$venv/bin/python" -c 'import xdist' 2>/dev/null; then
    parallel=(-n "$workers" --dist worksteal)  # idle workers take tests queued for busy ones
fi
status=0
"$venv/bin/python" -m pytest -q -p no:cacheprovider "${parallel[@]}" "$@" || status=$?
for f in "$note" "$note".gw*; do
    if [ -s "$f" ]; then  # pytest (or this worker) ended in the middle of a test
        worker=${f#"$note"}
        echo "tests/run.sh: pytest ended (exit status $status) while ${worker:+worker ${worker#.} ran }this test: $(cat "$f")" >&2
        [ "$status" -ne 0 ] || status=1
    fi
    rm -f "$f"
done

# Whoever reads this script's output (CI) waits until no process holds it any
# more. A process started during the run that still holds it (our standard
# output or error) is named and ended, so the run ends with the tests.
# (tests/conftest.py ends what the tests left; this also covers the install.)
start_time() {  # a process's start, in clock ticks since boot (field 22 of /proc/PID/stat)
    local stat
    stat=$(cat "/proc/$1/stat" 2>/dev/null) || return 1
    stat=${stat##*) }  # past the command name, which may hold spaces
    set -- $stat
    echo "${20}"
}
parent_of() {  # a process's parent (field 4 of /proc/PID/stat)
    local stat
    stat=$(cat "/proc/$1/stat" 2>/dev/null) || return 1
    stat=${stat##*) }
    set -- $stat
    echo "$2"
}
started=$(start_time $$ || true)
# who started this script (a CI wrapper, `timeout`) holds the output too, and may have begun
# in the same clock tick: never ours to end
ancestors=" "
pid=$$
while pid=$(parent_of "$pid") && [ "$pid" -gt 1 ]; do ancestors="$ancestors$pid "; done
for fd in 1 2; do
    target=$(readlink "/proc/$$/fd/$fd" 2>/dev/null || true)
    case "$target" in pipe:*|socket:*) ;; *) continue ;; esac
    for dir in /proc/[0-9]*; do
        pid=${dir#/proc/}
        [ "$pid" = "$$" ] && continue
        case "$ancestors" in *" $pid "*) continue ;; esac
        [ "$(readlink "$dir/fd/1" 2>/dev/null)" = "$target" ] ||
            [ "$(readlink "$dir/fd/2" 2>/dev/null)" = "$target" ] || continue
        begun=$(start_time "$pid" || echo 0)
        [ -n "$started" ] && [ "$begun" -ge "$started" ] || continue  # ours began before: the reader's side
        echo "tests/run.sh: process $pid ($(tr '\0' ' ' < "$dir/cmdline" 2>/dev/null | cut -c1-160)) still holds the output after the tests; ending it" >&2
        kill -TERM "$pid" 2>/dev/null || true
        sleep 2
        kill -KILL "$pid" 2>/dev/null || true
    done
done
exit "$status"
