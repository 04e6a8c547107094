"""Small widgets shared by the window's parts."""

from __future__ import annotations

from typing import Optional

from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

__all__ = ["ElidedLabel"]


class ElidedLabel(QtWidgets.QLabel):
    """One line of text cut with "…" to the room it gets; the full text is its tooltip.

    For the status bar and other single lines that must never widen the window.
    ``text()`` returns the full text.
    """

    def __init__(self, text: str = "", parent=None, *, min_chars: int = 6, min_text: str = ""):
        super().__init__(parent)
        self._full = ""
        self._shown = ""
        self._min_chars = int(min_chars)
        self._min_text = str(min_text)  # never cut below this text's width
        self.setSizePolicy(QtWidgets.QSizePolicy.Preferred, QtWidgets.QSizePolicy.Preferred)
        self.setText(text)

    def setText(self, text: str, shown: Optional[str] = None) -> None:  # noqa: N802 - Qt name
        """``text`` (what :meth:`text` returns, and the tooltip); ``shown``: fewer words to paint instead."""
        text = str(text)
        shown = text if shown is None else str(shown)
        if text == self._full and shown == self._shown:
            return
        self._full, self._shown = text, shown
        self.setToolTip(text)
        self.updateGeometry()
        self._elide()

    def text(self) -> str:
        return self._full

    def shown_text(self) -> str:
        """What is painted (possibly cut with "…")."""
        return super().text()

    def sizeHint(self):
        fm = self.fontMetrics()
        m = self.contentsMargins()
        return QtCore.QSize(fm.horizontalAdvance(self._shown) + m.left() + m.right() + 4,
                            super().sizeHint().height())

    def minimumSizeHint(self):
        fm = self.fontMetrics()
        m = self.contentsMargins()
        least = max(fm.horizontalAdvance("x" * self._min_chars),
                    fm.horizontalAdvance(self._min_text) + m.left() + m.right() + 4 if self._min_text else 0)
        return QtCore.QSize(least, super().minimumSizeHint().height())

    def resizeEvent(self, ev):
        super().resizeEvent(ev)
        self._elide()

    def _elide(self):
        m = self.contentsMargins()
        width = max(self.width() - m.left() - m.right() - 2, 0)
        shown = self.fontMetrics().elidedText(self._shown, QtCore.Qt.ElideRight, width)
        if shown != super().text():
            super().setText(shown)
