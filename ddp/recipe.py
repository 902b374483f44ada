"""YAML recipes: loading, ``base:`` inheritance, dotted overrides.

A recipe is a YAML mapping. ``base: other.yaml`` (a path relative to the
recipe, or a list of them) is loaded first and the recipe is merged on top:
mappings merge key by key, everything else (lists included) replaces. A
plugin section whose ``name`` differs from the base's swaps the part: it
replaces the base section whole, since the old part's options would not fit.
Overrides ``a.b.c=value`` (value parsed as YAML) are applied last.
Every error is one line naming the file and the dotted key.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any, Iterable

import re

import yaml

from ddp.errors import RecipeError

BASE_KEY = "base"


class RecipeLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 scalars: ``lr: 3e-4`` is a float, not the string '3e-4', and
    ``seed: 010`` is 10, not octal 8 (``0o10`` is 8, ``0x10`` 16; ``1:30`` and ``1:30.5`` are strings, not
    sexagesimal 90 / 90.5); only true / false are booleans (``on``, ``off``, ``yes``, ``no`` are strings) and
    ``2024-06-01`` is a string, not a date."""


_INT, _FLOAT, _BOOL = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float", "tag:yaml.org,2002:bool"
_YAML11_ONLY = {_INT, _FLOAT, _BOOL, "tag:yaml.org,2002:timestamp"}  # replaced below by their YAML 1.2 forms
RecipeLoader.yaml_implicit_resolvers = {
    k: [(tag, rx) for tag, rx in v if tag not in _YAML11_ONLY]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
RecipeLoader.add_implicit_resolver(_BOOL, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
RecipeLoader.add_implicit_resolver(_INT, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
                                   list("-+0123456789"))


def _construct_int(loader: yaml.SafeLoader, node: yaml.Node) -> int:
    text = loader.construct_scalar(node)
    if text.startswith(("0o", "0x")):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text, 10)


RecipeLoader.add_constructor(_INT, _construct_int)
RecipeLoader.add_implicit_resolver(  # YAML 1.2's core schema (no '_' separators, one sign at most)
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _mapping_without_duplicates(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict:
    """A YAML mapping; a key given twice is an error (YAML forbids it; PyYAML keeps the last silently)."""
    seen: dict = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge" or not isinstance(key_node, yaml.ScalarNode):
            continue  # '<<' merges (construct_mapping flattens them) and complex keys
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, (str, int, float, bool)) or key is None:
            continue  # an unhashable or odd key: construct_mapping reports it
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{key}' (first given on line {seen[key] + 1})", key_node.start_mark
            )
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=True)


RecipeLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_duplicates)


class RecipeDumper(yaml.SafeDumper):
    """PyYAML's safe dumper that quotes every string either YAML 1.1 or :class:`RecipeLoader` (YAML 1.2) would
    read as something else: ``'1e-3'`` (a string) was written bare and read back as 0.001."""


RecipeDumper.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()}
for _first, _resolvers in RecipeLoader.yaml_implicit_resolvers.items():
    RecipeDumper.yaml_implicit_resolvers.setdefault(_first, []).extend(_resolvers)


def load_yaml(text: str) -> Any:
    """Parse recipe YAML (safe: plain data only) with YAML 1.2 number syntax."""
    return yaml.load(text, Loader=RecipeLoader)  # noqa: S506 (RecipeLoader is a SafeLoader)


def _read_yaml(path: Path, *, referenced_by: str | None = None) -> dict:
    try:
        text = path.read_text()
    except FileNotFoundError:
        if referenced_by is not None:
            raise RecipeError(f"base recipe '{path}' not found", source=referenced_by, key=BASE_KEY) from None
        raise RecipeError("recipe file not found", source=str(path)) from None
    except OSError as err:
        raise RecipeError(f"cannot read recipe: {err.strerror}", source=str(path)) from None
    except UnicodeDecodeError as err:
        raise RecipeError(f"not a text file (byte {err.start} is not UTF-8): a recipe is YAML text",
                          source=str(path)) from None
    try:
        data = load_yaml(text)
    except ValueError as err:  # a scalar a resolver took for a number its constructor refused
        raise RecipeError(f"malformed YAML: {err}", source=str(path)) from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise RecipeError(f"malformed YAML at {where}{problem}", source=str(path)) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise RecipeError(f"a recipe must be a YAML mapping, got {type(data).__name__}", source=str(path))
    return data


def _same_part(a: dict, b: dict) -> bool:
    return "name" not in a or "name" not in b or a["name"] == b["name"]


def merge(base: dict, top: dict) -> dict:
    """Recursive merge: mappings merge, other values (lists too) replace.

    Mappings naming different plugins (``name`` differs) do not merge: the top one wins whole.
    """
    out = copy.deepcopy(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and _same_part(out[key], value):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_yaml_tree(path: str | os.PathLike, _chain: tuple[Path, ...] = (), _referenced_by: str | None = None) -> dict:
    """Load a recipe file and resolve its ``base:`` chain (no validation). A relative path under ``recipes/``
    that the working directory lacks names the copy shipped with the package (:func:`ddp.shipped.locate`)."""
    from ddp.shipped import locate

    path = locate(path) if not _chain else Path(path)
    resolved = path.resolve()
    if resolved in _chain:
        cycle = " -> ".join(str(p) for p in (*_chain, resolved))
        raise RecipeError(f"cyclic base: {cycle}", source=_referenced_by, key=BASE_KEY)
    data = _read_yaml(path, referenced_by=_referenced_by)
    bases = data.pop(BASE_KEY, None)
    if bases is None:
        return data
    if isinstance(bases, str):
        bases = [bases]
    if not isinstance(bases, list) or not all(isinstance(b, str) for b in bases):
        raise RecipeError(f"must be a path or a list of paths, got {bases!r}", source=str(path), key=BASE_KEY)
    merged: dict = {}
    for base in bases:
        base_path = (path.parent / base) if not os.path.isabs(base) else Path(base)
        merged = merge(merged, load_yaml_tree(base_path, (*_chain, resolved), str(path)))
    return merge(merged, data)


_KEY_PART = re.compile(r"^([A-Za-z0-9_-]+)((?:\[[0-9]+\])*)$")


def parse_override(text: str) -> tuple[list[str | int], Any]:
    """``"policy.scheduler.num_inference_steps=5"`` -> (["policy", ...], 5); a list item is addressed by its
    index, ``"controller.subtasks[0].target=1"`` -> (["controller", "subtasks", 0, "target"], 1)."""
    if not isinstance(text, str) or "=" not in text:
        raise RecipeError(f"bad override {text!r}: expected key.path=value", source="--set")
    key, _, raw = text.partition("=")
    key = key.strip()
    parts: list[str | int] = []
    for piece in key.split(".") if key else [""]:
        match = _KEY_PART.match(piece)
        if match is None:
            raise RecipeError(f"bad override {text!r}: '{key}' is not a dotted key like a.b.c (or a.b[0].c)",
                              source="--set")
        parts.append(match.group(1))
        parts.extend(int(i) for i in re.findall(r"\[([0-9]+)\]", match.group(2)))
    try:
        value = load_yaml(raw) if raw.strip() else None
    except (yaml.YAMLError, ValueError):
        raise RecipeError(f"bad override {text!r}: the value is not valid YAML", source="--set", key=key) from None
    return parts, value


def _dotted(parts: list[str | int]) -> str:
    """``["a", "b", 0, "c"]`` -> ``"a.b[0].c"``."""
    return "".join(f"[{p}]" if isinstance(p, int) else (f".{p}" if i else p) for i, p in enumerate(parts))


def apply_overrides(data: dict, overrides: Iterable[str]) -> dict:
    """``data`` with each ``key.path=value`` set, in order. Setting a part's ``name`` to another plugin
    starts that section afresh, as a recipe merge does: the options the recipe gave the old part are
    dropped (they belong to it), the ones other ``--set``s give the section are kept, whatever their order."""
    out = copy.deepcopy(data)
    written: set[tuple] = set()  # the full key paths --set wrote
    switched_on: dict[tuple, str] = {}  # a section the recipe sets to null -> the first --set writing into it
    for text in overrides:
        parts, value = parse_override(text)
        section = tuple(parts[:-1])
        written.add(tuple(parts))
        node = out
        for i, part in enumerate(parts):
            last = i == len(parts) - 1
            where = _dotted(parts[:i])
            if isinstance(part, int):  # a list item: it must exist (a list is not grown by --set)
                if not isinstance(node, list):
                    raise RecipeError(f"cannot set '{_dotted(parts)}': '{where}' is {node!r}, not a list",
                                      source="--set", key=_dotted(parts))
                if part >= len(node):
                    raise RecipeError(f"cannot set '{_dotted(parts)}': '{where}' has {len(node)} items "
                                      f"(indices 0..{len(node) - 1})", source="--set", key=_dotted(parts))
            elif not isinstance(node, dict):
                raise RecipeError(f"cannot set '{_dotted(parts)}': '{where}' is {node!r}, not a mapping",
                                  source="--set", key=_dotted(parts))
            if last:
                if part == "name" and section and isinstance(node.get("name"), str) and node["name"] != value:
                    _keep_written(node, section, written)  # the old part's options go (a merge drops them too)
                node[part] = value
            else:
                child = node[part] if isinstance(part, int) else node.get(part)
                if child is None and isinstance(parts[i + 1], int):  # nothing to index: a default is not here yet
                    raise RecipeError(f"cannot set '{_dotted(parts)}': the recipe does not set "
                                      f"'{_dotted(parts[:i + 1])}' (its default list is not indexable here): "
                                      "set the whole list",
                                      source="--set", key=_dotted(parts))
                if child is None:
                    if isinstance(part, str) and part in node:  # the recipe turns this section off (null)
                        switched_on.setdefault(tuple(parts[:i + 1]), _dotted(parts))
                    child = node[part] = {}
                node = child
    _check_switched_on(out, switched_on)
    return out


def _keep_written(node: dict, path: tuple, written: set[tuple]) -> None:
    """Drop from the section ``node`` (at ``path``) every option that no ``--set`` wrote, at any depth."""
    for key in [k for k in node if k != "name"]:
        below = (*path, key)
        if below in written:
            continue
        if isinstance(node[key], dict) and any(w[:len(below)] == below for w in written):
            _keep_written(node[key], below, written)
        else:
            del node[key]


def _check_switched_on(data: dict, switched_on: dict[tuple, str]) -> None:
    """A plugin section the recipe turns off (``tracker: null``) gets options from --set only with a plugin
    name: it does not silently become the default plugin."""
    from ddp.schema import PART_SECTIONS  # (schema imports nothing from here at module level)

    for path, key in switched_on.items():
        section = _dotted(list(path))
        node = data
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        if section in PART_SECTIONS and isinstance(node, dict) and "name" not in node:
            raise RecipeError(f"cannot set '{key}': the recipe sets '{section}' to null (off); name the plugin "
                              f"to turn it on, e.g. --set {section}.name=...", source="--set", key=key)


def load_recipe(path: str | os.PathLike | dict, overrides: Iterable[str] = ()) -> tuple[dict, str]:
    """The merged, overridden recipe as a plain dict, and its source name."""
    if isinstance(path, dict):
        data, source = copy.deepcopy(path), "<dict>"
        bases = data.pop(BASE_KEY, None)
        if bases is not None:  # resolved against the working directory (a dict has no folder of its own)
            if isinstance(bases, str):
                bases = [bases]
            if not isinstance(bases, list) or not all(isinstance(b, str) for b in bases):
                raise RecipeError(f"must be a path or a list of paths, got {bases!r}", source=source, key=BASE_KEY)
            merged: dict = {}
            for base in bases:
                merged = merge(merged, load_yaml_tree(base, _referenced_by=source))  # (shipped copies too)
            data = merge(merged, data)
    else:
        data, source = load_yaml_tree(path), str(path)
    return apply_overrides(data, overrides), source


def dump_yaml(data: dict) -> str:
    """``data`` as YAML that :func:`load_yaml` reads back equal."""
    return yaml.dump(data, Dumper=RecipeDumper, sort_keys=False, default_flow_style=None)


def flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists are values)."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict) and value:
            out.update(flatten(value, dotted))
        else:
            out[dotted] = value
    return out


def recipe_changes(stored: dict, current: dict) -> dict[str, tuple[Any, Any]]:
    """Dotted keys whose value differs: ``{key: (stored, current)}``.

    A key the stored recipe lacks is not a change (it did not exist when that recipe was written).
    """
    old, new = flatten(stored), flatten(current)
    missing = object()
    changes = {}
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, missing), new.get(key, missing)
        if a is missing:
            continue
        if a != b:
            changes[key] = (a, None if b is missing else b)
    return changes
