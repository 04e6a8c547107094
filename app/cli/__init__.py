"""The ``tirdeflect`` console command (argument parsing and messages; the work is in
:mod:`app.batch`, :mod:`app.capture` and :mod:`app.gui`)."""

from app import version
from app.cli.main import build_parser, main

__all__ = ["main", "build_parser", "version"]
