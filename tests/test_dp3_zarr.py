"""The dp3_zarr data source: DP3-format zarr import/export round trip, down-sampling, errors.

No DP3 data can be downloaded here, so the project's own generated episodes
are exported in DP3's layout and imported back.
"""

import json
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from ddp.data.episodes import Episodes
from ddp.errors import DDPError, RecipeError
from ddp.schema import validate

zarr = pytest.importorskip("zarr")

from ddp.data.sources.dp3_zarr import DEFAULT_KEYS, export_dp3_zarr, read_dp3_zarr  # noqa: E402


def _source(data: dict, **recipe):
    rec, parts, _ = validate({"name": "z", "data": data, **recipe}, "<test>")
    return parts["data"].build(task=rec.task, seed=rec.seed, env=parts.get("env"))


@pytest.fixture(scope="module")
def demos():
    """Generated demos (synthetic_reach) with a 6-channel cloud (xyz + a fake colour) and an extra key."""
    eps = _source({"name": "synthetic_reach", "episodes": 3}, task={"num_points": 48}).load()
    steps = eps.steps
    rgb = torch.rand(*steps["point_cloud"].shape, generator=torch.Generator().manual_seed(0))
    steps = TensorDict(
        {
            "point_cloud": torch.cat([steps["point_cloud"], rgb], -1),
            "agent_pos": steps["agent_pos"],
            "action": steps["action"],
            "full_state": torch.randn(steps.batch_size[0], 39, generator=torch.Generator().manual_seed(1)),
        },
        batch_size=steps.batch_size,
    )
    return Episodes(steps, eps.episode_ends)


@pytest.fixture(scope="module")
def dp3_dir(demos, tmp_path_factory):
    return export_dp3_zarr(demos, tmp_path_factory.mktemp("dp3") / "metaworld_synthetic_expert.zarr", chunk_steps=16)


def test_export_writes_dp3_layout(dp3_dir, demos):
    assert json.loads((dp3_dir / ".zgroup").read_text())["zarr_format"] == 2
    meta = json.loads((dp3_dir / "data" / "point_cloud" / ".zarray").read_text())
    assert meta["shape"] == list(demos.steps["point_cloud"].shape) and meta["compressor"]["id"] == "blosc"
    root = zarr.open(str(dp3_dir), mode="r")
    assert np.array_equal(root["meta/episode_ends"][:], demos.episode_ends.numpy())
    assert np.array_equal(root["data/state"][:], demos.steps["agent_pos"].numpy())
    assert np.array_equal(root["data/full_state"][:], demos.steps["full_state"].numpy())
    with pytest.raises(DDPError, match="exists"):
        export_dp3_zarr(demos, dp3_dir)


def test_round_trip_identical_arrays(dp3_dir, demos):
    keys = {"point_cloud": "data/point_cloud", "agent_pos": "data/state", "action": "data/action",
            "full_state": "data/full_state"}  # fmt: skip
    back = read_dp3_zarr(dp3_dir, keys=keys, point_cloud_channels=6)
    assert torch.equal(back.episode_ends, demos.episode_ends)
    assert (back.steps == demos.steps).all()
    for k in keys:
        assert back.steps[k].dtype == torch.float32

    # through the registry, as a recipe's data section: xyz only by default
    loaded = _source({"name": "dp3_zarr", "path": str(dp3_dir)}, task={"num_points": 48}).load()
    assert set(loaded.steps.keys()) == {"point_cloud", "agent_pos", "action"}
    assert torch.equal(loaded.steps["point_cloud"], demos.steps["point_cloud"][..., :3])
    assert torch.equal(loaded.episode_ends, demos.episode_ends)
    six = _source({"name": "dp3_zarr", "path": str(dp3_dir), "point_cloud_channels": 6},
                  task={"point_dim": 6, "num_points": 48}).load()  # fmt: skip
    assert torch.equal(six.steps["point_cloud"], demos.steps["point_cloud"])


@pytest.mark.parametrize("method", ["fps", "random"])
def test_subsampling_is_deterministic_and_keeps_stored_points(dp3_dir, demos, method):
    data = {"name": "dp3_zarr", "path": str(dp3_dir), "num_points": 16, "subsample": method,
            "point_cloud_channels": 6}  # fmt: skip
    a = _source(data, task={"point_dim": 6, "num_points": 16}).load()
    b = _source(data, task={"point_dim": 6, "num_points": 16}).load()
    assert a.steps["point_cloud"].shape == (demos.num_steps, 16, 6)
    assert torch.equal(a.steps["point_cloud"], b.steps["point_cloud"])
    assert torch.equal(a.steps["action"], demos.steps["action"])
    full = demos.steps["point_cloud"]
    for t in (0, demos.num_steps // 2, demos.num_steps - 1):
        # every kept point (with its colour) is one of the stored points of that frame, none twice
        match = (a.steps["point_cloud"][t][:, None, :] == full[t][None, :, :]).all(-1)
        assert (match.sum(1) >= 1).all()
        assert torch.unique(match.float().argmax(1)).numel() == 16
    if method == "fps":
        # FPS starts at the first stored point and spreads out: its minimum pairwise distance beats a prefix's
        assert torch.equal(a.steps["point_cloud"][:, 0], full[:, 0])
        kept = a.steps["point_cloud"][0, :, :3]
        prefix = full[0, :16, :3]
        gap = lambda p: (torch.cdist(p, p) + 1e9 * torch.eye(16)).min()  # noqa: E731
        assert gap(kept) > gap(prefix)
    else:
        assert not torch.equal(a.steps["point_cloud"][:, :16], full[:, :16])  # a subset, not the first points


def test_errors_name_the_path_and_the_key(dp3_dir, tmp_path):
    missing = tmp_path / "nope.zarr"
    with pytest.raises(DDPError, match=f"{missing}: no such DP3 zarr directory"):
        _source({"name": "dp3_zarr", "path": str(missing)}).load()
    with pytest.raises(DDPError, match=rf"{dp3_dir}: no array 'data/pc'.*found: data/action"):
        read_dp3_zarr(dp3_dir, keys={"point_cloud": "data/pc", "agent_pos": "data/state", "action": "data/action"})
    with pytest.raises(DDPError, match="num_points is 4096 but data/point_cloud holds 48 points"):
        read_dp3_zarr(dp3_dir, num_points=4096)
    with pytest.raises(DDPError, match="point_cloud_channels is 9 but data/point_cloud has 6 channels"):
        read_dp3_zarr(dp3_dir, point_cloud_channels=9)
    with pytest.raises(DDPError, match="task.agent_pos_dim is 7 but the data have 9"):
        _source({"name": "dp3_zarr", "path": str(dp3_dir)}, task={"agent_pos_dim": 7, "num_points": 48}).load()
    with pytest.raises(RecipeError, match="keys must map point_cloud, agent_pos, action; missing action"):
        _source({"name": "dp3_zarr", "path": "x", "keys": {"point_cloud": "a", "agent_pos": "b"}})
    (tmp_path / "empty.zarr").mkdir()
    with pytest.raises(DDPError, match="empty.zarr: not a readable zarr store"):
        read_dp3_zarr(tmp_path / "empty.zarr")


def test_inconsistent_lengths_are_reported(demos, tmp_path):
    path = export_dp3_zarr(demos, tmp_path / "bad.zarr")
    root = zarr.open(str(path), mode="r+")
    ends = root["meta/episode_ends"]
    ends[-1] = int(ends[-1]) - 1
    with pytest.raises(DDPError, match=r"data/point_cloud has \d+ steps but meta/episode_ends ends at"):
        read_dp3_zarr(path)


def test_non_numeric_arrays_are_refused_before_reading(demos, tmp_path):
    """zarr 2 decodes an object array by unpickling it: a DP3 zarr someone sent must not run code, so any
    array that is not numbers is refused, by name, before it is read."""
    path = export_dp3_zarr(demos, tmp_path / "odd.zarr")
    root = zarr.open(str(path), mode="r+")
    steps = root["data/action"].shape[0]
    del root["data/action"]
    root.create_array("data/action", shape=(steps,), dtype="<U4")
    with pytest.raises(DDPError, match=r"odd.zarr: data/action has dtype <U4; only numeric arrays are read"):
        read_dp3_zarr(path)


def test_clouds_are_sampled_to_the_recipes_point_count(dp3_dir, demos):
    # data.num_points: null samples to task.num_points (FPS), as the model is built for
    eps = _source({"name": "dp3_zarr", "path": str(dp3_dir)}, task={"num_points": 20}).load()
    assert eps.steps["point_cloud"].shape == (demos.num_steps, 20, 3)
    with pytest.raises(DDPError, match=r"data.num_points \(16\) differs from task.num_points \(20\)"):
        _source({"name": "dp3_zarr", "path": str(dp3_dir), "num_points": 16}, task={"num_points": 20}).load()
    with pytest.raises(DDPError, match="num_points is 512 but data/point_cloud holds 48 points"):
        _source({"name": "dp3_zarr", "path": str(dp3_dir)}).load()  # never padded


def test_colour_clouds_train_end_to_end(dp3_dir, tiny_recipe, tmp_path):
    """xyz+rgb clouds (point_dim 6, use_color) fit the normaliser on all six channels and train."""
    from ddp import build
    from ddp.errors import RecipeError

    tiny_recipe.update(
        data={"name": "dp3_zarr", "path": str(dp3_dir), "point_cloud_channels": 6},
        encoder={"name": "dp3", "use_color": True},
    )
    tiny_recipe["task"].update(point_dim=6, num_points=48)
    tiny_recipe["train"].update(max_steps=2, epochs=1)
    del tiny_recipe["env"]
    exp = build(tiny_recipe)
    res = exp.train(output_dir=tmp_path, progress=False)
    assert res.steps == 2 and math.isfinite(res.loss)
    assert exp.model.normalizer.point_cloud_scale.shape == (6,)
    assert not torch.equal(exp.model.normalizer.point_cloud_scale[3:], torch.ones(3))  # rgb was fitted too
    tiny_recipe["task"]["point_dim"] = 3
    with pytest.raises(RecipeError, match="encoder: encoder.use_color reads xyz.rgb points: set task.point_dim to 6"):
        build(tiny_recipe)


def test_overwriting_keeps_the_earlier_store_until_the_new_one_is_in_place(demos, tmp_path, monkeypatch):
    import os

    path = export_dp3_zarr(demos, tmp_path / "store.zarr")
    before = zarr.open(str(path), mode="r")["data/action"][:]
    real_rename = os.rename

    def failing_rename(src, dst):  # the new store's move into place fails (a crash, a full disk)
        if ".tmp" in str(src) and str(dst) == str(path):
            raise OSError("no space left on device")
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", failing_rename)
    with pytest.raises(OSError, match="no space left"):
        export_dp3_zarr(Episodes(demos.steps[:10], torch.tensor([4, 10])), path, overwrite=True)
    monkeypatch.setattr(os, "rename", real_rename)
    assert np.array_equal(zarr.open(str(path), mode="r")["data/action"][:], before)  # the earlier store, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store.zarr"]  # nothing left beside it
    export_dp3_zarr(Episodes(demos.steps[:10], torch.tensor([4, 10])), path, overwrite=True)
    assert zarr.open(str(path), mode="r")["data/action"].shape[0] == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["store.zarr"]


def test_missing_chunks_are_refused_not_read_as_zeros(demos, tmp_path):
    """zarr reads a chunk file that is not there as the fill value: a partly copied store imported with zero
    actions, silently. A required array with chunks missing is refused; an extra key warns."""
    path = export_dp3_zarr(demos, tmp_path / "partial.zarr", chunk_steps=4)
    for chunk in (path / "data" / "action").iterdir():
        if not chunk.name.startswith("."):
            chunk.unlink()
            break
    with pytest.raises(DDPError, match=r"partial.zarr: data/action: 1 of \d+ chunks are not stored.*"
                                       r"data.fill_missing_chunks: true reads them"):
        read_dp3_zarr(path)
    with pytest.warns(RuntimeWarning, match=r"data/action: 1 of \d+ chunks are not stored"):  # the opt-in
        assert read_dp3_zarr(path, fill_missing=True).num_episodes == 3
    path = export_dp3_zarr(demos, tmp_path / "extra.zarr", chunk_steps=4)
    next(c for c in (path / "data" / "full_state").iterdir() if not c.name.startswith(".")).unlink()
    with pytest.warns(RuntimeWarning, match=r"data/full_state: 1 of \d+ chunks are not stored"):
        read_dp3_zarr(path, keys={**DEFAULT_KEYS, "full_state": "data/full_state"})


def test_zero_chunks_are_written_and_read_back(demos, tmp_path):
    """zarr 3 leaves a chunk of only the fill value unwritten by default: the export writes every chunk, so its
    own stores (a still stretch of zero actions) import again."""
    steps = demos.steps.clone()
    steps["action"][:8] = 0.0
    path = export_dp3_zarr(Episodes(steps, demos.episode_ends), tmp_path / "still.zarr", chunk_steps=4)
    back = read_dp3_zarr(path)
    assert torch.equal(back.steps["action"], steps["action"])


def test_unsafe_codecs_and_damaged_metadata_are_refused_unread(demos, tmp_path):
    """A numeric dtype with a pickle filter or compressor (zarr 2 unpickles the chunk whatever the dtype) is
    refused by name before zarr reads it; unreadable metadata and float episode ends are one-line errors."""
    for field, codec in (("filters", [{"id": "pickle"}]), ("compressor", {"id": "pickle", "protocol": 5})):
        path = export_dp3_zarr(demos, tmp_path / f"{field}.zarr")
        meta_file = path / "data" / "action" / ".zarray"
        meta = json.loads(meta_file.read_text())
        meta[field] = codec
        meta_file.write_text(json.dumps(meta))
        with pytest.raises(DDPError, match=r"data/action is stored with codec 'pickle'; only numeric codecs"):
            read_dp3_zarr(path)
    path = export_dp3_zarr(demos, tmp_path / "garbled.zarr")
    (path / "data" / "state" / ".zarray").write_text("{not json")
    with pytest.raises(DDPError, match=r"data/state: unreadable array metadata .zarray") as err:
        read_dp3_zarr(path)
    assert "\n" not in str(err.value)
    (tmp_path / "store.zip").write_bytes(b"PK")  # zarr 2 opens a zip file as a store: its codecs go unseen
    with pytest.raises(DDPError, match=r"store.zip: not a directory; only directory zarr stores are read"):
        read_dp3_zarr(tmp_path / "store.zip")
    path = export_dp3_zarr(demos, tmp_path / "consolidated.zarr")  # metadata zarr reads from elsewhere: unseen
    zarr.consolidate_metadata(str(path))
    (path / "data" / "action" / ".zarray").unlink()
    with pytest.raises(DDPError, match=r"data/action has no .zarray / zarr.json file on disk"):
        read_dp3_zarr(path)
    path = export_dp3_zarr(demos, tmp_path / "float_ends.zarr")
    root = zarr.open(str(path), mode="r+")
    ends = root["meta/episode_ends"][:]
    del root["meta/episode_ends"]
    root.create_array("meta/episode_ends", shape=ends.shape, dtype="<f8")[...] = ends.astype(np.float64)
    with pytest.raises(DDPError, match=r"meta/episode_ends holds float64 of shape \(3,\), expected a 1-D integer"):
        read_dp3_zarr(path)


def test_overwrite_replaces_only_a_store(demos, tmp_path):
    """export_dp3_zarr(..., "data", overwrite=True) wiped any folder; it now replaces a store or an empty folder."""
    precious = tmp_path / "precious"
    (precious / "sub").mkdir(parents=True)
    (precious / "sub" / "notes.txt").write_text("keep")
    with pytest.raises(DDPError, match=r"precious: exists and is not a zarr store"):
        export_dp3_zarr(demos, precious, overwrite=True)
    assert (precious / "sub" / "notes.txt").read_text() == "keep"
    (tmp_path / "empty").mkdir()
    assert read_dp3_zarr(export_dp3_zarr(demos, tmp_path / "empty", overwrite=True)).num_episodes == 3
