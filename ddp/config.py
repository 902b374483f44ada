"""Typed config dataclasses <-> plain dicts, with errors that name the key.

Every pluggable part declares a ``@dataclass`` config. A recipe's options are
validated against it here: unknown options (with the closest valid one),
wrong types and missing required options all raise :class:`RecipeError`
naming the recipe file and the dotted key.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Any, Literal, Union, get_args, get_origin

from ddp.errors import RecipeError, suggest

_MISSING = dataclasses.MISSING


def _join(prefix: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return f"{prefix}.{key}" if prefix else str(key)


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    if origin in (Union, types.UnionType):
        return " | ".join(_type_name(a) for a in get_args(tp))
    if origin is not None:
        args = ", ".join(_type_name(a) for a in get_args(tp) if a is not Ellipsis)
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp: Any, key: str, source: str | None) -> Any:
    """Check ``value`` against the annotation ``tp``; return the typed value."""

    def fail(expected: str | None = None) -> RecipeError:
        return RecipeError(
            f"expected {expected or _type_name(tp)}, got {value!r} ({type(value).__name__})",
            source=source,
            key=key,
        )

    if tp is Any:
        return value
    origin = get_origin(tp)
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            hint = suggest(value, [str(c) for c in choices]) if isinstance(value, str) else ""
            raise RecipeError(
                f"must be one of {', '.join(repr(c) for c in choices)}; got {value!r}{hint}",
                source=source,
                key=key,
            )
        return value
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise fail()
        value_errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return coerce(value, arg, key, source)
            except RecipeError as err:
                if err.reason.startswith("must be"):  # the type fits but the value does not (e.g. NaN)
                    value_errors.append(err)
        if value_errors:
            raise value_errors[0]
        raise fail()
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise fail()
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise fail(f"{_type_name(tp)} of length {len(args)}")
            items = [coerce(v, a, _join(key, i), source) for i, (v, a) in enumerate(zip(value, args))]
        else:
            item_tp = args[0] if args else Any
            items = [coerce(v, item_tp, _join(key, i), source) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise fail()
        ktp, vtp = get_args(tp) or (Any, Any)
        return {coerce(k, ktp, key, source): coerce(v, vtp, _join(key, str(k)), source) for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise fail(f"a mapping of {tp.__name__} options")
        return from_dict(tp, value, key=key, source=source)
    if tp is bool:
        if not isinstance(value, bool):
            raise fail()
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail()
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise fail()
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an int too large for a float
            finite = False
        if not finite:
            shown = value if isinstance(value, float) else f"{str(value)[:12]}... ({len(str(value))} digits)"
            raise RecipeError(f"must be a finite number; got {shown}", source=source, key=key)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise fail()
        return value
    if isinstance(tp, type):
        if not isinstance(value, tp):
            raise fail()
        return value
    return value


def field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _literal_choices(tp: Any) -> tuple:
    """The values a ``Literal[...]`` (or ``Literal[...] | None``) annotation admits; ``()`` for other types."""
    if get_origin(tp) is Literal:
        return get_args(tp)
    if get_origin(tp) in (Union, types.UnionType):
        args = get_args(tp)
        if all(a is type(None) or get_origin(a) is Literal for a in args):  # Literal[...] | Literal[...] | None
            return tuple(c for a in args if a is not type(None) for c in get_args(a)) + \
                ((None,) if type(None) in args else ())
    return ()


@functools.cache
def _choice_fields(cls: type) -> tuple[tuple[str, tuple], ...]:
    return tuple((name, c) for name, tp in field_types(cls).items() if (c := _literal_choices(tp)))


def check_choices(cfg: Any, prefix: str = "") -> None:
    """One-line ``ValueError`` for a ``Literal``-typed field of the dataclass ``cfg`` holding another value.

    For configs built in Python (recipes are already checked by :func:`from_dict`); call it from
    ``__post_init__``. ``prefix`` is put before the field's name (e.g. ``"env.real."``).
    """
    for name, choices in _choice_fields(type(cfg)):
        value = getattr(cfg, name)
        if value not in choices:
            hint = suggest(value, [str(c) for c in choices]) if isinstance(value, str) else ""
            raise ValueError(f"{prefix}{name} must be one of {', '.join(repr(c) for c in choices)}; got {value!r}{hint}")


def from_dict(cls: type, data: dict | None, *, key: str = "", source: str | None = None):
    """Build the dataclass ``cls`` from ``data``, validating every option.

    ``__post_init__`` may raise ``ValueError``: it is re-raised as a
    :class:`RecipeError` naming ``key``.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise RecipeError(f"expected a mapping of {cls.__name__} options, got {data!r}", source=source, key=key or None)
    types_ = field_types(cls)
    for name in data:
        if name not in types_:
            raise RecipeError(
                f"unknown option{suggest(name, types_)} (valid: {', '.join(types_)})",
                source=source,
                key=_join(key, name),
            )
    kwargs = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if f.name in data and data[f.name] is None and types_[f.name] is dict and f.default_factory is not _MISSING:
            kwargs[f.name] = f.default_factory()  # null for a mapping option: its default (an overlay clears a base's)
        elif f.name in data:
            kwargs[f.name] = coerce(data[f.name], types_[f.name], _join(key, f.name), source)
        elif f.default is _MISSING and f.default_factory is _MISSING:
            raise RecipeError("missing required option", source=source, key=_join(key, f.name))
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as err:
        raise RecipeError(str(err), source=source, key=key or None) from None


def to_dict(cfg: Any) -> Any:
    """A dataclass (tree) as plain YAML-able Python values."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if f.init}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def without_neutral_defaults(options: dict, config_cls: type) -> dict:
    """``options`` (a config as a dict) without the keys written at the value ``config_cls`` declares neutral
    (its ``cache_neutral_defaults``: options added after caches and results existed, whose default is what ran
    before), so spelling out such a default changes no hash. Lists and tuples compare as sequences."""
    neutral = getattr(config_cls, "cache_neutral_defaults", None) or {}

    def same(value, default) -> bool:
        if isinstance(value, (list, tuple)) and isinstance(default, (list, tuple)):
            return list(value) == list(default)
        return value == default

    return {k: v for k, v in options.items() if not (k in neutral and same(v, neutral[k]))}
