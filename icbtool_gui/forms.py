"""Settings forms generated from frozen config dataclasses (``dataclasses.fields`` -> widgets).

One widget per field, chosen from its type: ``bool`` a check box, ``Literal[...]`` a combo box,
``int`` a spin box, anything else (floats, strings, optional values, tuples) a line edit whose
text is parsed back to the field's type. The field's docstring is the widget's tool tip. The
dataclass itself validates: :meth:`DataclassForm.value` builds it, so a bad entry raises the
config's own ``ValueError``.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any, Literal, get_args, get_origin

from PySide6 import QtCore, QtWidgets

from icbtool.configdoc import field_docs


def _is_optional(tp: Any) -> tuple[bool, Any]:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) < len(get_args(tp)):
            return True, args[0] if len(args) == 1 else typing.Union[tuple(args)]  # noqa: UP007
    return False, tp


def parse_text(text: str, tp: Any, name: str) -> Any:
    """Parse a line edit's ``text`` as type ``tp`` (field ``name``, for the message).

    Raises:
        ValueError: the text is not a value of that type.
    """
    text = text.strip()
    optional, inner = _is_optional(tp)
    if optional and text in ("", "None"):
        return None
    try:
        if inner is float:
            return float(text)
        if inner is int:
            return int(text)
        if inner is str:
            return text
        if get_origin(inner) is tuple:
            args = get_args(inner)
            parts = [p for p in text.replace("(", "").replace(")", "").split(",") if p.strip()]
            kinds = args if args and args[-1] is not Ellipsis else [args[0]] * len(parts)
            if len(kinds) != len(parts):
                raise ValueError(f"needs {len(kinds)} comma-separated values")
            return tuple(k(p.strip()) for k, p in zip(kinds, parts, strict=True))
        if get_origin(inner) in (typing.Union, types.UnionType):  # e.g. Literal["auto"] | float
            for a in get_args(inner):
                try:
                    return parse_text(text, a, name)
                except ValueError:
                    continue
            raise ValueError("matches none of the allowed types")
        if get_origin(inner) is Literal:
            allowed = get_args(inner)
            for a in allowed:
                if str(a) == text:
                    return a
            raise ValueError(f"must be one of {list(allowed)}")
        return json.loads(text)  # dicts, lists, Any
    except (ValueError, TypeError, json.JSONDecodeError) as e:
        raise ValueError(f"{name}: cannot read {text!r} as {_type_name(tp)} ({e})") from None


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def format_value(v: Any) -> str:
    """The line-edit text of a value (``parse_text`` reads it back)."""
    if v is None:
        return ""
    if isinstance(v, tuple):
        return ", ".join(format_value(x) for x in v)
    if isinstance(v, (dict, list)):
        return json.dumps(v)
    return str(v)


def call_repr(value: Any, prefix: str = "") -> str:
    """``Name(field=value, ...)`` of a dataclass instance, listing only the fields that differ
    from their defaults (the Python a script would write)."""
    parts = []
    for f in dataclasses.fields(value):
        v = getattr(value, f.name)
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        try:
            same = bool(v == default)
        except ValueError:  # numpy arrays
            same = False
        if not same:
            parts.append(f"{f.name}={v!r}")
    return f"{prefix}{type(value).__name__}({', '.join(parts)})"


class DataclassForm(QtWidgets.QWidget):
    """A form with one widget per field of a (frozen) dataclass instance.

    Args:
        value: the initial value (its class defines the fields).
        exclude: field names not shown (they keep ``value``'s).
        parent: Qt parent.

    Signals:
        changed: any widget was edited.
    """

    changed = QtCore.Signal()

    def __init__(
        self, value: Any, exclude: tuple[str, ...] = (), parent: QtWidgets.QWidget | None = None
    ) -> None:
        super().__init__(parent)
        if not dataclasses.is_dataclass(value) or isinstance(value, type):
            raise TypeError(f"DataclassForm needs a dataclass instance, got {value!r}")
        self.cls = type(value)
        self._base = value
        self._hints = typing.get_type_hints(self.cls)
        self._docs = field_docs(self.cls)
        self.widgets: dict[str, QtWidgets.QWidget] = {}
        layout = QtWidgets.QFormLayout(self)
        layout.setFieldGrowthPolicy(QtWidgets.QFormLayout.AllNonFixedFieldsGrow)
        for f in dataclasses.fields(self.cls):
            if f.name in exclude or not f.init:
                continue
            w = self._widget(f.name, self._hints.get(f.name, Any))
            w.setObjectName(f.name)
            w.setToolTip(self._docs.get(f.name, ""))
            self.widgets[f.name] = w
            label = QtWidgets.QLabel(f.name)
            label.setToolTip(self._docs.get(f.name, ""))
            layout.addRow(label, w)
        self.set_value(value)

    def _widget(self, name: str, tp: Any) -> QtWidgets.QWidget:
        if tp is bool:
            w = QtWidgets.QCheckBox()
            w.toggled.connect(self.changed)
            return w
        if get_origin(tp) is Literal:
            w = QtWidgets.QComboBox()
            w.addItems([str(a) for a in get_args(tp)])
            w.currentIndexChanged.connect(self.changed)
            return w
        if tp is int:
            w = QtWidgets.QSpinBox()
            w.setRange(-(2**31) + 1, 2**31 - 1)
            w.valueChanged.connect(self.changed)
            return w
        w = QtWidgets.QLineEdit()
        w.editingFinished.connect(self.changed)
        return w

    def set_value(self, value: Any) -> None:
        """Show ``value`` (an instance of the form's class)."""
        if type(value) is not self.cls:
            raise TypeError(f"expected a {self.cls.__name__}, got {type(value).__name__}")
        self._base = value
        for name, w in self.widgets.items():
            v = getattr(value, name)
            w.blockSignals(True)
            if isinstance(w, QtWidgets.QCheckBox):
                w.setChecked(bool(v))
            elif isinstance(w, QtWidgets.QComboBox):
                w.setCurrentIndex(max(0, w.findText(str(v))))
            elif isinstance(w, QtWidgets.QSpinBox):
                w.setValue(int(v))
            else:
                w.setText(format_value(v))
            w.blockSignals(False)

    def set_field(self, name: str, v: Any) -> None:
        """Set one field's widget (as a user would) without validating yet."""
        self.set_value(dataclasses.replace(self.value(), **{name: v}))

    def value(self) -> Any:
        """The dataclass built from the widgets.

        Raises:
            ValueError: a widget's text cannot be read, or the dataclass rejects the values.
        """
        kw: dict[str, Any] = {}
        for name, w in self.widgets.items():
            if isinstance(w, QtWidgets.QCheckBox):
                kw[name] = w.isChecked()
            elif isinstance(w, QtWidgets.QComboBox):
                kw[name] = parse_text(w.currentText(), self._hints[name], name)
            elif isinstance(w, QtWidgets.QSpinBox):
                kw[name] = int(w.value())
            else:
                kw[name] = parse_text(w.text(), self._hints.get(name, Any), name)
        return dataclasses.replace(self._base, **kw)


__all__ = ["DataclassForm", "call_repr", "field_docs", "format_value", "parse_text"]
