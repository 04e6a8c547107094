"""The window's menu bar and keyboard shortcuts (one table: menus, Help ▸ Keyboard shortcuts, docs/gui.md).

:data:`SHORTCUTS` is the single list of what a key does; :func:`build_menus`
puts every entry into its menu with its key, the Help dialog lists the same
table, and a test checks that the "Shortcuts" table of docs/gui.md says the
same. Menu entries whose window method is not there (e.g. a build without
experiment files) are shown disabled instead of failing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

__all__ = ["SHORTCUTS", "Shortcut", "build_menus", "shortcuts_text", "DOCS_PATH", "SCENES"]

DOCS_PATH = Path(__file__).resolve().parents[2] / "docs" / "gui.md"

#: scenes of the synthetic camera (``MainWindow.set_scene(name)``)
SCENES = ("still", "waves", "drop", "impact")


class Shortcut(NamedTuple):
    """One menu entry: ``name`` (the QAction's object name), menu, text shown, keys, what it does."""

    name: str
    menu: str
    action: str
    keys: str


SHORTCUTS = (
    Shortcut("open_recording", "File", "Open recording…", "Ctrl+O"),
    Shortcut("open_experiment", "File", "Open experiment…", "Ctrl+Shift+O"),
    Shortcut("save_experiment", "File", "Save experiment…", "Ctrl+S"),
    Shortcut("snapshot", "File", "Snapshot (window PNG + maps HDF5)", "F12"),
    Shortcut("export", "File", "Export heights of the open recording…", "Ctrl+E"),
    Shortcut("export_movie", "File", "Export movie of processed heights (OUT.h5)…", "Ctrl+M"),
    Shortcut("quit", "File", "Quit", "Ctrl+Q"),
    Shortcut("capture_reference", "Measure", "Capture reference", "Ctrl+R"),
    Shortcut("arm", "Measure", "Arm recording", "Ctrl+Shift+A"),
    Shortcut("trigger", "Measure", "Trigger now", "Ctrl+T"),
    Shortcut("disarm", "Measure", "Disarm", "Ctrl+Shift+D"),
    Shortcut("pause", "View", "Pause display", "Ctrl+Space"),
    Shortcut("tab_live", "View", "Live tab", "Ctrl+1"),
    Shortcut("tab_alignment", "View", "Alignment tab", "Ctrl+2"),
    Shortcut("tab_replay", "View", "Replay tab", "Ctrl+3"),
    Shortcut("controls", "View", "Show/hide the Controls panel", "Ctrl+D"),
    Shortcut("clear_probes", "View", "Remove all probes (click the height map to place one)", "Ctrl+Shift+P"),
    Shortcut("gpu", "View", "Live reconstruction on the GPU (remembered)", ""),
    Shortcut("scene_still", "View", "Synthetic scene: still water", "Alt+1"),
    Shortcut("scene_waves", "View", "Synthetic scene: travelling waves", "Alt+2"),
    Shortcut("scene_drop", "View", "Synthetic scene: drop (ring waves)", "Alt+3"),
    Shortcut("scene_impact", "View", "Synthetic scene: impact (approaching disc)", "Alt+4"),
    Shortcut("help_shortcuts", "Help", "Keyboard shortcuts", "F1"),
    Shortcut("help_docs", "Help", "Documentation", ""),
    Shortcut("help_about", "Help", "About tirdeflect", ""),
)


def shortcuts_text() -> str:
    """The shortcut table as Markdown (``action | keys``), as docs/gui.md has it."""
    rows = ["| action | keys |", "|---|---|"]
    rows += [f"| {s.action} | {s.keys} |" for s in SHORTCUTS if s.keys]
    return "\n".join(rows)


def _file_dialog(window, save: bool, title: str, default: str, filters: str):
    fn = QtWidgets.QFileDialog.getSaveFileName if save else QtWidgets.QFileDialog.getOpenFileName
    path, _ = fn(window, title, default, filters)
    return path


def _handlers(window) -> dict:
    """What each entry does; None where the window lacks the method (entry disabled)."""

    def experiment(save: bool):
        name = "save_experiment" if save else "open_experiment"
        if not hasattr(window, name):
            return None

        def run():
            path = _file_dialog(window, save, "Save experiment" if save else "Open experiment",
                                "experiment.toml" if save else "", "Experiment (*.toml)")
            if path:
                getattr(window, name)(path)
        return run

    def scene(name: str):
        if not hasattr(window, "set_scene"):
            return None
        return lambda: window.set_scene(name)

    def tab(i: int):
        return lambda: window.tabs.setCurrentIndex(i)

    from . import export

    rp, gp = window.recording_panel, window.geometry_panel
    handlers = {
        "open_recording": window._choose_recording,
        "open_experiment": experiment(False),
        "save_experiment": experiment(True),
        "snapshot": window.snapshot,
        "export": window._choose_export,
        "export_movie": lambda: export.choose_movie(window),
        "clear_probes": window.probe_view.clear if hasattr(window, "probe_view") else None,
        "quit": window.close,
        # the panels' own buttons: the same checks (enabled state) as a click
        "capture_reference": gp.capture_button.click,
        "arm": rp.arm_button.click,
        "trigger": rp.trigger_button.click,
        "disarm": rp.disarm_button.click,
        "pause": window.pause_box.toggle,
        "tab_live": tab(0),
        "tab_alignment": tab(1),
        "tab_replay": tab(2),
        "controls": lambda: window.controls_dock.setVisible(not window.controls_dock.isVisible()),
        "help_shortcuts": lambda: show_shortcuts(window),
        "help_docs": lambda: show_documentation(window),
        "help_about": lambda: show_about(window),
    }
    for name in SCENES:
        handlers[f"scene_{name}"] = scene(name)
    return handlers


def build_menus(window) -> dict:
    """Fill ``window.menuBar()`` from :data:`SHORTCUTS`; returns ``{name: QAction}`` (also ``window.actions_by_name``)."""
    bar = window.menuBar()
    menus = {}
    actions = {}
    handlers = _handlers(window)
    for s in SHORTCUTS:
        menu = menus.get(s.menu)
        if menu is None:
            menu = menus[s.menu] = bar.addMenu("&" + s.menu)
        if s.name == "pause":
            menu.addSeparator()
        if s.name.startswith("scene_"):  # every scene in View ▸ Synthetic scene
            if "View ▸ scene" not in menus:
                menus["View ▸ scene"] = menu.addMenu("Synthetic scene")
            menu = menus["View ▸ scene"]
        act = QtGui.QAction(s.action, window)
        act.setObjectName(s.name)
        if s.keys:
            act.setShortcut(QtGui.QKeySequence(s.keys))
            act.setShortcutContext(QtCore.Qt.WindowShortcut)
        fn = handlers.get(s.name)
        if s.name == "gpu":  # a remembered setting: checked as the session left it
            act.setCheckable(True)
            act.setChecked(window.memory.use_gpu)
            act.setToolTip("off: the live maps are computed on the CPU; on: on the GPU when CuPy sees one "
                           "(the status bar says which)")
            act.toggled.connect(window.use_gpu)
        elif s.name == "pause":  # mirrors the status bar's check box
            act.setCheckable(True)
            window.pause_box.toggled.connect(act.setChecked)
            act.triggered.connect(lambda _checked=False, act=act: window.pause_box.setChecked(act.isChecked()))
        elif fn is None:
            act.setEnabled(False)
            act.setToolTip("not available in this build")
        else:
            act.triggered.connect(lambda _checked=False, fn=fn: fn())
        menu.addAction(act)
        actions[s.name] = act
    window.actions_by_name = actions
    return actions


def show_shortcuts(window) -> QtWidgets.QMessageBox:
    rows = "".join(f"<tr><td>{s.action}</td><td><b>{s.keys}</b></td></tr>" for s in SHORTCUTS if s.keys)
    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Information, "Keyboard shortcuts",
                                f"<table cellpadding=3>{rows}</table>", QtWidgets.QMessageBox.Close, window)
    box.setTextFormat(QtCore.Qt.RichText)
    box.setModal(False)
    box.show()
    window.help_box = box
    return box


def show_documentation(window) -> None:
    """docs/gui.md of this installation in the desktop's viewer; where there is none, say where it is."""
    url = QtCore.QUrl.fromLocalFile(str(DOCS_PATH))
    opened = DOCS_PATH.exists() and os.environ.get("QT_QPA_PLATFORM") != "offscreen" and \
        QtGui.QDesktopServices.openUrl(url)
    if not opened:
        window.info(f"documentation: {DOCS_PATH} (and docs/ beside it; README.md for the method)")


def show_about(window) -> QtWidgets.QMessageBox:
    from app import version

    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Information, "About tirdeflect",
                                f"tirdeflect {version()}\n\nLive total-internal-reflection deflectometry: "
                                "water-surface heights from the distortion of a pattern seen through the "
                                f"surface.\n\nDocumentation: {DOCS_PATH.parent}", QtWidgets.QMessageBox.Close,
                                window)
    box.setModal(False)
    box.show()
    window.help_box = box
    return box
