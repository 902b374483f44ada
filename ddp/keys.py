"""TensorDict key handling shared by every part: declared, defaulted, renamable."""

from __future__ import annotations

from typing import Sequence, Union

from tensordict.nn import TensorDictModuleBase

from ddp.errors import suggest

NestedKey = Union[str, tuple[str, ...]]


class KeyedModule(TensorDictModuleBase):
    """A TensorDict module whose keys have defaults and can be renamed.

    Subclasses set ``default_in_keys`` / ``default_out_keys`` (dicts from a
    role name to a TensorDict key). ``set_keys(point_cloud="pc")`` renames;
    an unknown role raises with the list of valid roles.
    """

    default_in_keys: dict[str, NestedKey] = {}
    default_out_keys: dict[str, NestedKey] = {}

    def __init__(self) -> None:
        super().__init__()
        self._keys: dict[str, NestedKey] = {**self.default_in_keys, **self.default_out_keys}
        self._sync_keys()

    def _sync_keys(self) -> None:
        self.in_keys = [self._keys[r] for r in self.default_in_keys]
        self.out_keys = [self._keys[r] for r in self.default_out_keys]

    def set_keys(self, **roles: NestedKey) -> "KeyedModule":
        for role, key in roles.items():
            if role not in self._keys:
                raise KeyError(
                    f"{type(self).__name__} has no key role '{role}'{suggest(role, self._keys)} "
                    f"(roles: {', '.join(self._keys)})"
                )
            self._keys[role] = key
        self._sync_keys()
        return self

    def key(self, role: str) -> NestedKey:
        return self._keys[role]


def flatten_batch(x, event_dims: int):
    """Flatten all leading batch dims of ``x`` into one; return (x, batch_shape)."""
    batch_shape = x.shape[: x.dim() - event_dims]
    return x.reshape(-1, *x.shape[x.dim() - event_dims :]), batch_shape


def roles(keys: Sequence[NestedKey]) -> list[NestedKey]:
    return list(keys)
