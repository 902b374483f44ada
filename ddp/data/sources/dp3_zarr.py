"""DP3-format zarr demonstrations: train on data generated with the DP3 code base.

DP3 (and FlowPolicy) store demos as a zarr v2 directory (a "replay buffer"):

* ``data/point_cloud`` ``[T, P, 3 or 6]`` (xyz, optionally rgb),
* ``data/state`` ``[T, D]`` (agent_pos: 9-d on MetaWorld),
* ``data/action`` ``[T, A]``,
* ``meta/episode_ends`` ``[E]`` (exclusive end index of each episode),

plus arrays this loader does not need (``data/img``, ``data/depth``,
``data/full_state``; list them in ``keys`` to import them too). Episodes are
stored back to back, which is how :class:`ddp.data.episodes.Episodes`
stores them, so the import is a copy (and an optional down-sampling of the
clouds); :func:`export_dp3_zarr` writes the same layout.

Needs the ``zarr`` package (2.x or 3.x; both read and write the v2 format).
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tensordict import TensorDict

from ddp.atomic_file import atomic_directory
from ddp.data.episodes import Episodes
from ddp.data.sources.episodes_dir import check_task
from ddp.errors import DDPError
from ddp.registry import register

__all__ = ["DP3ZarrConfig", "DP3Zarr", "DEFAULT_KEYS", "export_dp3_zarr", "read_dp3_zarr"]

#: episode key -> array inside the zarr group (DP3's names)
DEFAULT_KEYS: dict[str, str] = {"point_cloud": "data/point_cloud", "agent_pos": "data/state", "action": "data/action"}
REQUIRED = ("point_cloud", "agent_pos", "action")
EPISODE_ENDS = "meta/episode_ends"
_READ_CHUNK = 1024  # frames read (and down-sampled) at a time


def _zarr():
    try:
        import zarr
    except ImportError as err:
        raise ImportError(f'DP3 zarr data needs the zarr package ({err}): pip install zarr (or "ddp[sim]")') from None
    return zarr


@dataclass
class DP3ZarrConfig:
    """Options of the ``dp3_zarr`` data source.

    Attributes:
        path: the ``.zarr`` directory (e.g. DP3's ``data/metaworld_button-press_expert.zarr``).
        point_cloud_channels: channels kept per point (3 = xyz; 6 = xyz + rgb, if stored).
        num_points: down-sample each cloud to this many points (null: ``task.num_points``, the
            count the model is built for; a value that differs from it is refused). Fewer stored
            points than that is an error: clouds are never padded.
        subsample: ``"fps"`` (farthest point sampling from the first point, on xyz) or
            ``"random"`` (a seeded random subset per frame); both deterministic.
        subsample_seed: seed of ``"random"``.
        keys: episode key -> zarr array; must map point_cloud, agent_pos and action. Extra
            entries (e.g. ``full_state: data/full_state``) are imported as extra keys.
        fill_missing_chunks: read chunks a required array does not store as its fill value (zarr leaves a
            chunk of only that value unwritten unless told otherwise) instead of refusing the store.
    """

    path: str
    point_cloud_channels: int = 3
    num_points: int | None = None
    subsample: Literal["fps", "random"] = "fps"
    subsample_seed: int = 0
    keys: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_KEYS))
    fill_missing_chunks: bool = False

    def __post_init__(self):
        if not self.path:
            raise ValueError("path must not be empty")
        if self.point_cloud_channels < 3:
            raise ValueError(f"point_cloud_channels must be >= 3 (xyz first); got {self.point_cloud_channels}")
        if self.num_points is not None and self.num_points < 1:
            raise ValueError(f"num_points must be >= 1 or null; got {self.num_points}")
        missing = [k for k in REQUIRED if k not in self.keys]
        if missing:
            raise ValueError(f"keys must map {', '.join(REQUIRED)}; missing {', '.join(missing)} (got {self.keys})")


def _subsample(cloud: np.ndarray, n: int, method: str, rng: np.random.Generator) -> np.ndarray:
    """``[t, P, C] -> [t, n, C]`` (``n <= P``)."""
    if method == "random":
        idx = np.argsort(rng.random(cloud.shape[:2]), axis=1)[:, :n]
    else:
        from ddp.envs.pointcloud import farthest_point_sample

        idx = np.stack([farthest_point_sample(frame[:, :3], n) for frame in cloud])
    return np.take_along_axis(cloud, idx[:, :, None], axis=1)


def read_dp3_zarr(
    path: str | os.PathLike,
    *,
    keys: dict[str, str] | None = None,
    point_cloud_channels: int = 3,
    num_points: int | None = None,
    subsample: str = "fps",
    subsample_seed: int = 0,
    fill_missing: bool = False,
) -> Episodes:
    """Read a DP3 zarr replay buffer into :class:`Episodes` (float arrays as float32). A chunk not stored in a
    required array is an error unless ``fill_missing`` (it then reads as the fill value, with a warning)."""
    zarr = _zarr()
    path = Path(path).expanduser()
    keys = dict(DEFAULT_KEYS if keys is None else keys)
    if not path.exists():
        raise DDPError(f"{path}: no such DP3 zarr directory")
    if not path.is_dir():
        raise DDPError(f"{path}: not a directory; only directory zarr stores are read (unzip a zipped store)")
    try:
        root = zarr.open(str(path), mode="r")
    except Exception as err:  # noqa: BLE001 - zarr raises several types for "not a zarr store"
        raise DDPError(f"{path}: not a readable zarr store ({type(err).__name__}: {err})") from None
    if not hasattr(root, "keys"):
        raise DDPError(f"{path}: is a single zarr array, expected a DP3 group with data/ and meta/")

    def array(name: str, *, required: bool = True):
        checked = _check_codecs(path, name)  # before zarr parses the metadata: a pickle codec would run code
        try:
            arr = root[name]
        except KeyError:
            found = sorted(_list_arrays(root))
            raise DDPError(
                f"{path}: no array '{name}' in the zarr store (found: {', '.join(found) or 'nothing'})"
            ) from None
        except (ValueError, TypeError) as err:
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise DDPError(f"{path}: {name}: unreadable array metadata ({first})") from None
        if not checked:  # zarr found it elsewhere (a zip, N5 or consolidated store): its codecs were not seen
            raise DDPError(f"{path}: {name} has no .zarray / zarr.json file on disk; only directory stores are "
                           "read (their codecs are checked before reading)")
        try:
            kind = np.dtype(arr.dtype).kind
        except TypeError:
            kind = "O"
        if kind not in "biuf":  # checked before reading: zarr 2 decodes an object array with pickle
            raise DDPError(f"{path}: {name} has dtype {arr.dtype}; only numeric arrays are read")
        stored, chunks = arr.nchunks_initialized, arr.nchunks
        if stored < chunks:  # zarr reads a chunk file that is not there as the fill value, without a word
            message = (f"{path}: {name}: {chunks - stored} of {chunks} chunks are not stored (a damaged or partly "
                       f"copied store, or chunks of only the fill value {arr.fill_value} left unwritten)")
            if required and not fill_missing:  # a stretch of zero clouds, states or actions is no demonstration
                raise DDPError(message + "; data.fill_missing_chunks: true reads them as the fill value")
            warnings.warn(message + f": they read as {arr.fill_value}", RuntimeWarning, stacklevel=3)
        return arr

    ends_array = array(EPISODE_ENDS)
    if np.dtype(ends_array.dtype).kind not in "iu" or len(ends_array.shape) != 1:
        raise DDPError(f"{path}: {EPISODE_ENDS} holds {ends_array.dtype} of shape {tuple(ends_array.shape)}, "
                       "expected a 1-D integer array of episode ends")
    ends = np.asarray(ends_array[:], dtype=np.int64)
    if ends.size == 0:
        raise DDPError(f"{path}: {EPISODE_ENDS} is empty (no episodes)")
    total = int(ends[-1])
    out: dict[str, torch.Tensor] = {}
    for name, zkey in keys.items():
        arr = array(zkey, required=name in REQUIRED)
        if arr.shape[0] != total:
            raise DDPError(f"{path}: {zkey} has {arr.shape[0]} steps but {EPISODE_ENDS} ends at {total}")
        if name == "point_cloud":
            out[name] = torch.from_numpy(
                _read_cloud(arr, path, zkey, point_cloud_channels, num_points, subsample, subsample_seed)
            )
            continue
        data = np.asarray(arr[:])
        if np.issubdtype(data.dtype, np.floating):
            data = data.astype(np.float32, copy=False)
        out[name] = torch.from_numpy(np.ascontiguousarray(data))
    try:
        return Episodes(TensorDict(out, batch_size=[total]), torch.from_numpy(ends))
    except ValueError as err:
        raise DDPError(f"{path}: {EPISODE_ENDS}: {err}") from None


def _read_cloud(arr, path, zkey, channels, num_points, method, seed) -> np.ndarray:
    if len(arr.shape) != 3:
        raise DDPError(f"{path}: {zkey} must be [T, P, C]; got shape {tuple(arr.shape)}")
    total, stored, stored_c = arr.shape
    if channels > stored_c:
        raise DDPError(f"{path}: point_cloud_channels is {channels} but {zkey} has {stored_c} channels")
    if num_points is not None and num_points > stored:
        raise DDPError(f"{path}: num_points is {num_points} but {zkey} holds {stored} points per frame")
    n = stored if num_points is None else num_points
    rng = np.random.default_rng(seed)
    result = np.empty((total, n, channels), dtype=np.float32)
    for s in range(0, total, _READ_CHUNK):
        block = np.asarray(arr[s : s + _READ_CHUNK, :, :channels], dtype=np.float32)
        if n < stored:
            block = _subsample(block, n, method, rng)
        result[s : s + block.shape[0]] = block
    return result


#: compressors and filters an array may name (zarr 2 ``id`` / zarr 3 codec ``name``, ``numcodecs.`` prefix
#: dropped): numeric codecs only; any other (``pickle``, ``json2``, ``msgpack2``, ...) is refused unread
_SAFE_CODECS = frozenset({
    "blosc", "zstd", "lz4", "zlib", "gzip", "bz2", "lzma", "delta", "fixedscaleoffset", "shuffle", "quantize",
    "bitround", "packbits", "astype", "crc32", "crc32c", "adler32", "fletcher32", "bytes", "endian", "transpose",
    "sharding_indexed",
})


def _check_codecs(path: Path, name: str) -> bool:
    """Refuse an array whose stored metadata names a codec outside :data:`_SAFE_CODECS`, read from the
    metadata file itself (zarr 2 applies ``numcodecs.Pickle`` to any dtype, ``<f4`` too). False when there is
    no metadata file of that array on disk."""
    folder = path.joinpath(*name.split("/"))
    ids: list = []
    if (folder / ".zarray").is_file():  # zarr format 2
        meta = _json(folder / ".zarray", path, name)
        for codec in [meta.get("compressor"), *(meta.get("filters") or [])]:
            if codec is not None:
                ids.append(codec.get("id") if isinstance(codec, dict) else codec)
    elif (folder / "zarr.json").is_file():  # zarr format 3 (a sharding codec holds codecs of its own)
        def walk(codecs):
            for codec in codecs or []:
                if not isinstance(codec, dict):
                    ids.append(codec)
                    continue
                ids.append(codec.get("name"))
                config = codec.get("configuration")
                if isinstance(config, dict):
                    walk(config.get("codecs"))
                    walk(config.get("index_codecs"))

        walk(_json(folder / "zarr.json", path, name).get("codecs"))
    else:
        return False  # no array of that name (the lookup names what the store holds), or not a directory store
    unsafe = [c for c in ids if not (isinstance(c, str) and c.removeprefix("numcodecs.") in _SAFE_CODECS)]
    if unsafe:
        raise DDPError(f"{path}: {name} is stored with codec {unsafe[0]!r}; only numeric codecs are read "
                       f"(refused unread: some codecs run code when decoding)")
    return True


def _json(file: Path, path: Path, name: str) -> dict:
    try:
        meta = json.loads(file.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise DDPError(f"{path}: {name}: unreadable array metadata {file.name} ({err})") from None
    if not isinstance(meta, dict):
        raise DDPError(f"{path}: {name}: {file.name} holds a {type(meta).__name__}, expected a mapping")
    return meta


def _list_arrays(group, prefix: str = "") -> list[str]:
    names = []
    for name in group.keys():
        node = group[name]
        full = f"{prefix}{name}"
        if hasattr(node, "keys") and not hasattr(node, "shape"):
            names += _list_arrays(node, full + "/")
        else:
            names.append(full)
    return names


def export_dp3_zarr(
    episodes: Episodes,
    path: str | os.PathLike,
    *,
    keys: dict[str, str] | None = None,
    chunk_steps: int = 100,
    overwrite: bool = False,
) -> Path:
    """Write episodes as a DP3 zarr v2 replay buffer (blosc/zstd compressed, every chunk written, zeros too),
    atomically. ``overwrite=True`` replaces an earlier store (or an empty folder), never another folder.

    ``keys`` maps episode keys to zarr arrays (default: DP3's names for
    point_cloud / agent_pos / action; any other episode key ``k`` goes to
    ``data/k``).
    """
    zarr = _zarr()
    import numcodecs

    path = Path(path).expanduser()
    if path.exists() and not overwrite:
        raise DDPError(f"{path}: exists (pass overwrite=True to replace it)")
    is_store = (path / ".zgroup").is_file() or (path / "zarr.json").is_file()
    if path.exists() and not is_store and (not path.is_dir() or any(path.iterdir())):
        raise DDPError(f"{path}: exists and is not a zarr store: overwrite=True replaces only a store (or an "
                       "empty folder)")
    keys = {**DEFAULT_KEYS, **(keys or {})}
    compressor = numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.SHUFFLE)
    v3 = int(zarr.__version__.split(".")[0]) >= 3

    def write(tmp: Path) -> None:
        root = zarr.open_group(str(tmp), mode="w", **({"zarr_format": 2} if v3 else {}))
        arrays = {keys.get(k, f"data/{k}"): episodes.steps[k].detach().cpu().numpy() for k in episodes.steps.keys()}
        arrays[EPISODE_ENDS] = episodes.episode_ends.cpu().numpy().astype(np.int64)
        for name, data in arrays.items():
            group_name, _, array_name = name.rpartition("/")
            group = root.require_group(group_name) if group_name else root
            chunks = (min(chunk_steps, max(1, data.shape[0])),) + tuple(data.shape[1:])
            if v3:
                z = group.create_array(array_name, shape=data.shape, chunks=chunks, dtype=data.dtype,
                                       compressors=compressor, config={"write_empty_chunks": True})  # fmt: skip
            else:
                z = group.create_dataset(array_name, shape=data.shape, chunks=chunks, dtype=data.dtype,
                                         compressor=compressor, write_empty_chunks=True)  # fmt: skip
            z[...] = data

    atomic_directory(path, write)  # an earlier store stays whole until the new one is in place
    return path


class DP3Zarr:
    """DP3-format zarr demonstrations (data/point_cloud, data/state, data/action, meta/episode_ends)."""

    def __init__(self, config: DP3ZarrConfig, *, task, seed: int = 0, env=None):
        self.cfg = config
        self.task = task
        self.path = Path(config.path).expanduser()

    def load(self) -> Episodes:
        cfg = self.cfg
        num_points = cfg.num_points
        if self.task is not None:
            if num_points is not None and num_points != self.task.num_points:
                raise DDPError(f"data.num_points ({num_points}) differs from task.num_points "
                               f"({self.task.num_points}): the model would train on other clouds than it sees")
            num_points = self.task.num_points  # the paper's FPS down to the recipe's count
        episodes = read_dp3_zarr(
            self.path,
            keys=cfg.keys,
            point_cloud_channels=cfg.point_cloud_channels,
            num_points=num_points,
            subsample=cfg.subsample,
            subsample_seed=cfg.subsample_seed,
            fill_missing=cfg.fill_missing_chunks,
        )
        check_task(episodes, self.task, str(self.path))
        return episodes


register("dataset", "dp3_zarr", config=DP3ZarrConfig)(DP3Zarr)
