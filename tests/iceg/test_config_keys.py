"""Every configuration key is read by code: a key no code reads is a bug (a knob that does
nothing). The check walks :class:`iceg.config.IcegConfig` recursively and looks for an attribute
access ``.key`` in the project's source outside the config models' own definitions."""

from __future__ import annotations

import ast
from pathlib import Path

from pydantic import BaseModel

from iceg.config import IcegConfig

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("iceg", "graph", "frontends", "iceg_common")


def _keys(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str]]:
    """``(dotted path, field name)`` of every field, sub-models included."""
    out = []
    for name, info in model.model_fields.items():
        out.append((prefix + name, name))
        ann = info.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out.extend(_keys(ann, prefix + name + "."))
    return out


def _attributes_read() -> set[str]:
    """Names read as attributes (``x.name``) or via ``getattr(x, "name")`` in the source."""
    names: set[str] = set()
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                    names.add(node.attr)
                elif (
                    isinstance(node, ast.Call)
                    and isinstance(node.func, ast.Name)
                    and node.func.id == "getattr"
                    and len(node.args) >= 2
                    and isinstance(node.args[1], ast.Constant)
                ):
                    names.add(str(node.args[1].value))
    return names


def test_config_has_sections_and_keys() -> None:
    keys = _keys(IcegConfig)
    assert len(keys) > 20
    assert ("grid.resolution_m", "resolution_m") in keys


def test_every_config_key_is_read_by_code() -> None:
    read = _attributes_read()
    unread = [path for path, name in _keys(IcegConfig) if name not in read]
    assert not unread, f"config keys no code reads (delete them or use them): {unread}"
