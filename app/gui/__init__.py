"""The live window (PySide6 + pyqtgraph): ``python3 -m app.gui`` or ``tirdeflect gui``."""
