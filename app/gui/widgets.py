"""Small widgets shared by the window's parts."""

from __future__ import annotations

from typing import Optional

from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

__all__ = ["ElidedLabel", "MessageArea"]


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


class MessageArea(QtWidgets.QScrollArea):
    """A message of any length, wrapped to the width it gets: as tall as its lines up to ``max_lines``, and
    scrolled beyond (a vertical scroll bar, the wheel), so that a long message never pushes the maps above
    it off the window nor is cut at the bottom of a small one.  The text can be selected and copied, and the
    full text is also the tooltip.  ``text()``, ``setText()``, ``styleSheet()`` and ``setStyleSheet()`` are
    the message label's, as on a QLabel."""

    def __init__(self, text: str = "", parent=None, *, max_lines: int = 4):
        super().__init__(parent)
        self.max_lines = int(max_lines)
        self.label = QtWidgets.QLabel()
        self.label.setTextFormat(QtCore.Qt.PlainText)  # "<= 8 %" in a message is no markup
        self.label.setWordWrap(True)
        self.label.setAlignment(QtCore.Qt.AlignLeft | QtCore.Qt.AlignTop)
        self.label.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        self.setWidget(self.label)
        self.setWidgetResizable(True)
        self.setFrameShape(QtWidgets.QFrame.NoFrame)
        self.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarAlwaysOff)
        self.setSizePolicy(QtWidgets.QSizePolicy.Preferred, QtWidgets.QSizePolicy.Fixed)
        self.verticalScrollBar().setSingleStep(self.label.fontMetrics().lineSpacing())  # a line an arrow click
        self.setText(text)

    def setText(self, text: str) -> None:  # noqa: N802 - Qt name
        text = str(text)
        if text == self.label.text():
            return  # (read where it was scrolled to)
        self.label.setText(text)
        self.setToolTip(text)
        self.verticalScrollBar().setValue(0)  # a new message is read from its first line
        self.updateGeometry()

    def text(self) -> str:
        return self.label.text()

    def setStyleSheet(self, sheet: str) -> None:  # noqa: N802 - Qt name
        self.label.setStyleSheet(sheet)
        self.updateGeometry()  # a bold font needs more lines

    def styleSheet(self) -> str:  # noqa: N802 - Qt name
        return self.label.styleSheet()

    def needed_height(self, width: Optional[int] = None) -> int:
        """Height (px) the whole message takes wrapped to ``width`` (the area's own width by default)."""
        return max(self.label.heightForWidth(max(self.width() if width is None else int(width), 1)), 0)

    def _shown_height(self) -> int:
        least = self.label.fontMetrics().lineSpacing()
        most = self.max_lines * least  # whole lines: no half line at the bottom
        needed = self.needed_height()
        return min(max(needed, least), most)  # beyond ``most`` it scrolls

    def sizeHint(self):
        return QtCore.QSize(super().sizeHint().width(), self._shown_height())

    def minimumSizeHint(self):
        return QtCore.QSize(super().minimumSizeHint().width(), self._shown_height())

    def resizeEvent(self, ev):
        super().resizeEvent(ev)
        if ev.oldSize().width() != ev.size().width():
            self.updateGeometry()  # another width, another number of lines
