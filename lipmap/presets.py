"""The one way to resolve a step's settings: a preset name, a dict of overrides, or the config itself.

Every step keeps its named presets in a module-level ``confs`` dict (hloc's habit) and resolves what
the caller gave with :func:`resolve`, so that all steps accept the same three forms and reject unknown
names and fields the same way.
"""
from __future__ import annotations

import copy
import dataclasses
from typing import Mapping, TypeVar, Union

from .errors import InputError

T = TypeVar("T")


def resolve(conf: Union[None, str, dict, T], presets: Mapping[str, T], kind: str, default: str) -> T:
    """The config that ``conf`` names.

    Args:
        conf: None (the ``default`` preset), a preset name, a dict ``{"preset": name, **field overrides}``
            (nested dataclass fields take dicts of overrides too) or a config instance (returned as is).
        presets: name -> config instance (dataclass).
        kind: what the configs configure, for error messages ("mapping", "2D line detector", ...).
        default: the preset used for None and for a dict without "preset".

    Returns:
        a copy of the preset with the overrides applied (presets themselves are never mutated).
    """
    proto = presets[default]
    if isinstance(conf, type(proto)):
        return conf
    if conf is None:
        return copy.deepcopy(proto)
    if isinstance(conf, str):
        return copy.deepcopy(_preset(conf, presets, kind))
    if isinstance(conf, Mapping):
        over = dict(conf)
        base = _preset(over.pop("preset", default), presets, kind)
        return _apply(copy.deepcopy(base), over, kind)
    raise InputError(f"{kind} settings must be a preset name, a dict or a {type(proto).__name__}, got {type(conf).__name__}")


def _preset(name: str, presets: Mapping, kind: str):
    if name not in presets:
        raise InputError(f"unknown {kind} preset {name!r}", hint=f"choose one of {', '.join(presets)}")
    return presets[name]


def _apply(obj, over: Mapping, kind: str):
    fields = {f.name: f for f in dataclasses.fields(obj)}
    unknown = sorted(set(over) - set(fields))
    if unknown:
        raise InputError(f"unknown {kind} setting(s) {', '.join(map(repr, unknown))}",
                         hint=f"valid: {', '.join(fields)}")
    values = {}
    for k, v in over.items():
        cur = getattr(obj, k)
        values[k] = _apply(cur, v, f"{kind}.{k}") if dataclasses.is_dataclass(cur) and isinstance(v, Mapping) else v
    return dataclasses.replace(obj, **values)
