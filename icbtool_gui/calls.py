"""The log of what the window did, as the equivalent Python (a script can replay it).

Every action of the window calls :meth:`CallLog.call` with the icbtool call it made, e.g.
``f = client.frame(path.camera_at(1.25), req)``; the lines go to the window's "Python" panel,
to the ``icbtool_gui`` logger (INFO) and stay in :attr:`CallLog.lines`.
"""

from __future__ import annotations

import logging

from PySide6 import QtCore, QtGui, QtWidgets

log = logging.getLogger("icbtool_gui")


class CallLog(QtCore.QObject):
    """The equivalent Python of the window's actions.

    Signals:
        logged(str): a new line (or block) of Python.
    """

    logged = QtCore.Signal(str)

    def __init__(self, parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self.lines: list[str] = []

    def call(self, code: str, comment: str = "") -> None:
        """Record ``code`` (one or more lines of Python), with an optional ``# comment``."""
        text = f"# {comment}\n{code}" if comment else code
        self.lines.append(text)
        log.info("%s", text)
        self.logged.emit(text)


class CallLogView(QtWidgets.QPlainTextEdit):
    """A read-only view of a :class:`CallLog`, newest line at the bottom."""

    def __init__(self, calls: CallLog, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setReadOnly(True)
        self.setLineWrapMode(QtWidgets.QPlainTextEdit.NoWrap)
        self.setFont(QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.FixedFont))
        self.setMaximumBlockCount(5000)
        for line in calls.lines:
            self.appendPlainText(line)
        calls.logged.connect(self.appendPlainText)


__all__ = ["CallLog", "CallLogView"]
