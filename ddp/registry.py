"""One registry per kind of part, filled by ``@register`` and by entry points.

Built-in parts live in the package named after their kind (``ddp.encoders``,
``ddp.schedulers``, ...): the modules of that package are imported the first
time its kind is looked up (importing ``ddp.evaluate`` or ``ddp.envs.chunked``
loads no simulator). Third-party packages add
parts through the entry-point group ``ddp.plugins`` (each entry point names a
module to import); those are loaded lazily on the first lookup of any kind.
Nothing is imported by a ``_target_`` string.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import importlib
import importlib.metadata
import importlib.util
import os
import sys
import warnings
from dataclasses import dataclass
from typing import Any, Callable

from ddp.errors import PluginError, RecipeError, closest

ENTRY_POINT_GROUP = "ddp.plugins"

#: kind -> (package holding the built-in parts, one-line description)
KINDS: dict[str, tuple[str, str]] = {
    "encoder": ("ddp.encoders", "observation -> latent per step (point cloud + proprioception)"),
    "denoiser": ("ddp.denoisers", "noise/sample/velocity network: (sample, timestep, condition) -> prediction"),
    "scheduler": ("ddp.schedulers", "diffusion / flow process: training loss and sampling loop"),
    "dataset": ("ddp.data.sources", "where demonstrations come from (synthetic, on disk, DP3 zarr, ...)"),
    "detector": ("ddp.detectors", "decides ID vs OOD from real and imagined latents"),
    "tracker": ("ddp.trackers", "estimates how far displaced objects moved"),
    "recovery": ("ddp.recovery", "undoes tracking shifts at subtask ends"),
    "trigger": ("ddp.triggers", "decides when a subtask has ended (gripper closure, timer, chunk index)"),
    "env": ("ddp.envs", "TorchRL environments (simulated or real)"),
    "protocol": ("ddp.protocols", "evaluation conditions: env disturbances plus a controller setting"),
}


@dataclass(frozen=True)
class Plugin:
    """A registered part: ``factory(config, **context)`` builds it."""

    kind: str
    name: str
    factory: Callable[..., Any]
    config_cls: type
    module: str

    @property
    def summary(self) -> str:
        doc = (self.factory.__doc__ or "").strip().splitlines()
        return doc[0].strip() if doc else ""


_REGISTRY: dict[str, dict[str, Plugin]] = {kind: {} for kind in KINDS}
_builtins_loaded: set[str] = set()
_entry_points_loaded = False
_failed: dict[str, str] = {}


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        near = closest(kind, KINDS, n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise PluginError(f"unknown plugin kind '{kind}'{hint} (kinds: {', '.join(KINDS)})")


def register(kind: str, name: str, *, config: type | None = None):
    """Class decorator: ``@register("detector", "discrepancy")``.

    The config dataclass is ``config`` or the decorated class's ``Config``
    attribute. A class is held against its kind's contract (:mod:`ddp.contracts`):
    a missing member is one ``PluginError`` line. Registering a name twice in
    one kind raises ``PluginError``.
    """
    _check_kind(kind)

    def decorate(obj):
        cfg = config if config is not None else getattr(obj, "Config", None)
        if cfg is None or not dataclasses.is_dataclass(cfg):
            raise PluginError(f"{kind} '{name}' ({obj.__module__}) must declare a config dataclass")
        if not isinstance(name, str) or not name:
            raise PluginError(f"{kind} plugin names are non-empty strings; {obj.__module__} gave {name!r}")
        if isinstance(obj, type):
            from ddp.contracts import check

            check(kind, obj, name=name, module=obj.__module__)
        if not _is_builtin(kind, obj.__module__):
            # a plugin imported before the first lookup (a recipe's plugins:, user code): the built-ins first, so
            # that taking a built-in name fails here, not in every later lookup of the process
            _load_builtins(kind)
        existing = _REGISTRY[kind].get(name)
        if existing is not None:
            raise PluginError(
                f"{kind} '{name}' is registered twice: by {existing.module} and by {obj.__module__}"
            )
        _REGISTRY[kind][name] = Plugin(kind, name, obj, cfg, obj.__module__)
        return obj

    return decorate


def _is_builtin(kind: str, module: str) -> bool:
    package = KINDS[kind][0]
    return module == package or module.startswith(package + ".")


def unregister(kind: str, name: str) -> None:
    """Remove a part (for tests and interactive sessions)."""
    _check_kind(kind)
    _REGISTRY[kind].pop(name, None)


def _load_builtins(kind: str) -> None:
    if kind in _builtins_loaded:
        return
    from ddp._autoload import import_submodules

    package = importlib.import_module(KINDS[kind][0])
    import_submodules(package.__name__, package.__path__)  # each module registers its parts
    _builtins_loaded.add(kind)  # only once they all registered (a failure is raised again on the next lookup)


def load_entry_points(force: bool = False) -> dict[str, str]:
    """Import every module named in the ``ddp.plugins`` entry-point group.

    A plugin that fails to import is reported by name (a warning) and
    remembered, so that a later "unknown name" error can mention it.
    Returns the failures as ``{entry point name: error}``.
    """
    global _entry_points_loaded
    if _entry_points_loaded and not force:
        return dict(_failed)
    _entry_points_loaded = True
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        before = {kind: dict(parts) for kind, parts in _REGISTRY.items()}
        try:
            ep.load()
        except Exception as err:  # noqa: BLE001 - report any import failure by name
            _restore(before)  # none of a failed plugin's parts (its module is gone: a worker could not import them)
            msg = f"{type(err).__name__}: {err}{shadowing_note(ep.module, getattr(ep, 'dist', None))}"
            _failed[ep.name] = msg
            warnings.warn(f"ddp plugin '{ep.name}' ({ep.value}) failed to import: {msg}", stacklevel=2)
    return dict(_failed)


def import_plugin_modules(modules: list[str], *, source: str | None = None, key: str = "plugins") -> None:
    """Import modules listed under a recipe's ``plugins:`` key."""
    for i, mod in enumerate(modules):
        before = {kind: dict(parts) for kind, parts in _REGISTRY.items()}
        try:
            importlib.import_module(mod)
        except Exception as err:  # noqa: BLE001
            _restore(before)
            raise RecipeError(
                f"cannot import plugin module '{mod}': {type(err).__name__}: {err}{shadowing_note(mod)}",
                source=source, key=f"{key}[{i}]",
            ) from None


def _restore(before: dict[str, dict]) -> None:
    """After an import that failed part-way: drop the parts registered since ``before`` by modules Python
    dropped with it (the failed module); parts of modules it imported successfully (built-ins, a package's
    own ``__init__``) stay, as those modules stay imported and would never register again."""
    for kind, parts in _REGISTRY.items():
        for name in [n for n, p in parts.items() if n not in before.get(kind, {}) and p.module not in sys.modules]:
            del parts[name]


def shadowing_note(module: str, dist=None) -> str:
    """`` (a folder ... shadows it)`` when ``module``'s top-level package resolves into the working directory
    (and not into the distribution that declared it); else an empty string."""
    top = str(module).split(".")[0]
    try:
        spec = importlib.util.find_spec(top)
    except Exception:  # noqa: BLE001 - a broken package is reported by the import error itself
        return ""
    if spec is None:
        return ""
    found = [os.path.abspath(p) for p in (spec.submodule_search_locations or [spec.origin]) if p]
    cwd = os.path.abspath(os.getcwd())
    inside = [p for p in found if p == cwd or p.startswith(cwd + os.sep)]
    if not inside:
        return ""
    if dist is None:  # a recipe's plugins: entry: the distribution that installed the package, if any
        names = importlib.metadata.packages_distributions().get(top, [])
        dist = next(iter(importlib.metadata.distribution(n) for n in names[:1]), None) if names else None
    if dist is None:
        return ""  # nothing installed under that name: a local module, not a shadowed one
    try:
        root = os.path.abspath(str(dist.locate_file("")))
    except Exception:  # noqa: BLE001
        return ""
    if any(p == root or p.startswith(root + os.sep) for p in inside):
        return ""  # the distribution itself lives here (a plugin developed in place)
    return f" ('{top}' resolves to {inside[0]}: a folder of that name in the working directory shadows the installed package)"


def _ensure(kind: str) -> None:
    """The built-in parts of every kind, then the entry-point plugins: a plugin that claims a built-in name
    fails to register (reported by name) instead of taking it over before the built-ins load."""
    _check_kind(kind)
    for k in KINDS:
        _load_builtins(k)
    load_entry_points()


def get(kind: str, name: str, *, source: str | None = None, key: str | None = None) -> Plugin:
    """Look a part up; an unknown name lists the closest and the known names."""
    _ensure(kind)
    table = _REGISTRY[kind]
    if name in table:
        return table[name]
    near = closest(name, table)
    hint = f"; did you mean {' or '.join(repr(n) for n in near)}?" if near else ""
    failed = f" (plugins that failed to import: {'; '.join(f'{n}: {m}' for n, m in _failed.items())})" if _failed else ""
    raise RecipeError(
        f"unknown {kind} '{name}'{hint} (known: {', '.join(sorted(table)) or 'none'}){failed}",
        source=source,
        key=key,
    )


def list_plugins(kind: str | None = None, pattern: str = "*") -> list[str] | dict[str, list[str]]:
    """Registered names of one kind matching a glob, or all kinds as a dict."""
    if kind is None:
        return {k: list_plugins(k, pattern) for k in KINDS}
    _ensure(kind)
    return sorted(n for n in _REGISTRY[kind] if fnmatch.fnmatch(n, pattern))


def plugins(kind: str) -> list[Plugin]:
    """The :class:`Plugin` records of one kind, sorted by name."""
    _ensure(kind)
    return [_REGISTRY[kind][n] for n in sorted(_REGISTRY[kind])]
