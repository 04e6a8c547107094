"""The app's worker processes (app/worker_processes.py): forked from one fork server that has
imported the reconstruction and loaded its compiled kernels, with the asking process's environment."""

import os

from app.worker_processes import adopt_parent_state, context, parent_state


def test_the_fork_servers_warm_up_reconstructs_its_frame():
    """The warm-up the server runs (a 96^2 synthetic frame, default options) runs through: were it to
    fail, every worker would load the kernels itself again (slower, nothing else wrong)."""
    from app.worker_preload import warm_up

    assert warm_up()


def _report(queue, given):
    adopt_parent_state(given)
    queue.put((os.environ.get("TIRDEFLECT_TEST_LATER"), os.getcwd(), os.getpid()))


def test_a_worker_started_later_takes_the_environment_and_folder_of_now(monkeypatch, tmp_path):
    """The fork server keeps the environment and working directory it started with; a worker handed
    :func:`parent_state` has those of this process when it was asked for."""
    ctx = context()
    queue = ctx.Queue()
    first = ctx.Process(target=_report, args=(queue, parent_state()))  # starts the server, if not yet
    first.start()
    queue.get(timeout=60)  # hang detector, far above the fraction of a second it takes
    first.join(60)
    monkeypatch.setenv("TIRDEFLECT_TEST_LATER", "set after the server started")
    monkeypatch.chdir(tmp_path)
    later = ctx.Process(target=_report, args=(queue, parent_state()))
    later.start()
    value, cwd, pid = queue.get(timeout=60)
    later.join(60)
    assert value == "set after the server started" and cwd == str(tmp_path)
    assert later.exitcode == 0 and pid != os.getpid()
