"""tirdeflect application, one sub-package per job.

- :mod:`app.capture`: camera thread, ring buffer, recorder, trigger, live processing worker,
  the synthetic tank scene;
- :mod:`app.files`: reading images, stacks and recordings; the cache directory;
- :mod:`app.batch`: the one batch engine (``tirdeflect process``, the GUI's export, scripts);
- :mod:`app.cli`: the ``tirdeflect`` command (argument parsing and messages only);
- :mod:`app.gui`: the live window (never imports :mod:`app.cli`).
"""

from __future__ import annotations

__all__ = ["version"]


def version() -> str:
    """tirdeflect's version (installed metadata, else pyproject.toml of this source tree)."""
    try:
        from importlib.metadata import PackageNotFoundError, version as _v

        try:
            return _v("tirdeflect")
        except PackageNotFoundError:
            pass
    except ImportError:  # pragma: no cover
        pass
    try:
        import tomllib
        from pathlib import Path

        data = tomllib.loads((Path(__file__).resolve().parent.parent / "pyproject.toml").read_text())
        return str(data["project"]["version"])
    except Exception:
        return "unknown"
