import pytest
import torch

from ddp.data.episodes import Episodes
from ddp.data.sequence import SequenceDataset, window_indices
from tensordict import TensorDict


def test_window_indices_pad_by_repeating_edge_frames():
    ends = torch.tensor([5, 8])
    idx = window_indices(ends, length=4, pad_before=1, pad_after=2)
    assert idx[0].tolist() == [0, 0, 1, 2]  # first frame repeated before the start
    ep0 = idx[(idx < 5).all(1)]
    assert ep0[-1].tolist() == [3, 4, 4, 4]  # last frame repeated after the end
    assert len(ep0) == (5 - 4 + 1) + 1 + 2  # 2 unpadded + 1 before + 2 after
    ep1 = idx[(idx >= 5).all(1)]
    assert ep1[0].tolist() == [5, 5, 6, 7] and ep1[-1].tolist() == [6, 7, 7, 7]
    assert ((idx < 5).all(1) | (idx >= 5).all(1)).all()  # windows never straddle episodes


def _episodes():
    eps = [
        TensorDict({"action": torch.arange(n, dtype=torch.float32).unsqueeze(-1) + 100 * i,
                    "agent_pos": torch.randn(n, 9)}, batch_size=[n])
        for i, n in enumerate([6, 9, 7])
    ]
    return Episodes.from_list(eps)


def test_episodes_save_load_round_trip(tmp_path):
    e = _episodes()
    e.save(tmp_path / "demos")
    back = Episodes.load(tmp_path / "demos")
    assert back.num_episodes == 3 and back.episode_ends.tolist() == [6, 15, 22]
    assert torch.equal(back.steps["agent_pos"], e.steps["agent_pos"])
    assert torch.equal(back.episode(1)["action"][:, 0], torch.arange(9.0) + 100)


def test_editing_loaded_episodes_in_place_leaves_the_files_alone(tmp_path):
    """Loaded episodes are mapped copy-on-write: user code normalising them in place changes its own copy,
    never the cache or dataset on disk (a shared mapping wrote the edit through)."""
    e = _episodes()
    e.save(tmp_path / "demos")
    back = Episodes.load(tmp_path / "demos")
    back.steps["agent_pos"].mul_(0)
    back.steps["action"][0] = -1
    assert back.steps["agent_pos"].abs().sum() == 0  # the edit holds in this process
    again = Episodes.load(tmp_path / "demos")
    assert torch.equal(again.steps["agent_pos"], e.steps["agent_pos"])
    assert torch.equal(again.steps["action"], e.steps["action"])


def test_episodes_that_cannot_be_mapped_privately_load_shared_with_a_warning(tmp_path, monkeypatch):
    """A private writable mapping is charged its whole size against the commit limit (strict overcommit on a
    cluster node can refuse it for a large dataset): the data then load as before, shared, and say so."""
    e = _episodes()
    e.save(tmp_path / "demos")

    real = torch.from_file

    def refused(*args, shared=False, **kwargs):  # the private mapping only (tensordict's shared one still works)
        if shared:
            return real(*args, shared=shared, **kwargs)
        raise RuntimeError("unable to mmap 2048 bytes from file: Cannot allocate memory (12)")

    monkeypatch.setattr(torch, "from_file", refused)
    with pytest.warns(RuntimeWarning, match="mapped shared, not copy-on-write .*Cannot allocate memory"):
        back = Episodes.load(tmp_path / "demos")
    assert torch.equal(back.steps["agent_pos"], e.steps["agent_pos"])


class _Payload:  # any picklable object: loading it would run code of the file's choosing
    pass


def test_loading_episodes_never_unpickles(tmp_path):
    """An episode directory whose steps hold a pickled leaf (tensordict writes other.pickle for a non-tensor)
    is refused in one line instead of unpickled (pickle runs code)."""
    import pytest
    from tensordict import NonTensorData

    from ddp.errors import DDPError

    e = _episodes()
    e.save(tmp_path / "demos")
    e.steps["x"] = NonTensorData(data=_Payload(), batch_size=e.steps.batch_size)
    e.save(tmp_path / "planted")
    assert (tmp_path / "planted" / "steps" / "x" / "other.pickle").exists()
    with pytest.raises(DDPError, match="something other than tensors"):
        Episodes.load(tmp_path / "planted")
    assert Episodes.load(tmp_path / "demos").num_episodes == 3


def test_damaged_episode_directories_are_one_line_errors(tmp_path):
    """A damaged meta.json, a pickled or missing episode_ends.pt, or boundaries that do not match the steps:
    each a one-line DDPError naming the file (they were tracebacks)."""
    import pytest

    from ddp.errors import DDPError

    def fresh(name):
        return _episodes().save(tmp_path / name)

    d = fresh("json")
    (d / "meta.json").write_text("{not json")
    with pytest.raises(DDPError, match=r"meta.json: not valid JSON"):
        Episodes.load(d)
    d = fresh("pickled")
    torch.save({"ends": _Payload()}, d / "episode_ends.pt")
    with pytest.raises(DDPError, match=r"episode_ends.pt: not a tensor file this loader reads \(refused") as err:
        Episodes.load(d)
    assert "\n" not in str(err.value)
    d = fresh("empty")
    (d / "episode_ends.pt").write_bytes(b"")  # a save killed mid-write
    with pytest.raises(DDPError, match=r"episode_ends.pt: not a tensor file this loader reads"):
        Episodes.load(d)
    for name, bad in (("twod", torch.tensor([[6, 15, 22]])), ("float", torch.tensor([6.0, 15.0, 22.0]))):
        d = fresh(name)
        torch.save(bad, d / "episode_ends.pt")
        with pytest.raises(DDPError, match=r"episode_ends.pt: holds a .* expected a 1-D integer tensor"):
            Episodes.load(d)
    d = fresh("missing")
    (d / "episode_ends.pt").unlink()
    with pytest.raises(DDPError, match=r"episode_ends.pt: missing"):
        Episodes.load(d)
    d = fresh("mismatch")
    torch.save(torch.tensor([6, 15, 21]), d / "episode_ends.pt")
    with pytest.raises(DDPError, match=r"mismatch: episode_ends must .* against the 22 stored steps"):
        Episodes.load(d)
    d = fresh("truncated")  # an interrupted copy: the action file cut short
    action = d / "steps" / "action.memmap"
    whole = action.stat().st_size
    with open(action, "r+b") as f:
        f.truncate(whole // 2)
    with pytest.raises(DDPError, match=rf"action.memmap: holds {whole // 2} bytes where its shape \[22, .*needs {whole}"):
        Episodes.load(d)
    assert action.stat().st_size == whole // 2  # refused before mapping: the file is left as it was
    d = fresh("steps_json")  # the data's own layout file: a bare JSONDecodeError naming no file
    (d / "steps" / "meta.json").write_text("{not json")
    with pytest.raises(DDPError, match=r"steps/meta.json: not valid JSON") as err:
        Episodes.load(d)
    assert "\n" not in str(err.value)
    d = fresh("steps_missing")  # a FileNotFoundError
    (d / "steps" / "meta.json").unlink()
    with pytest.raises(DDPError, match=r"steps/meta.json: missing"):
        Episodes.load(d)


def test_sequence_dataset_batches_match_items():
    ds = SequenceDataset(_episodes(), 5, pad_before=1, pad_after=3)
    b = ds.batch(torch.tensor([0, 4, len(ds) - 1]))
    assert b.batch_size == (3, 5)
    assert torch.equal(b[1]["action"], ds[4]["action"])
    assert ds[0]["action"][:, 0].tolist() == [0, 0, 1, 2, 3]


def test_saving_over_episodes_is_atomic(tmp_path, monkeypatch):
    """An interrupted save leaves the earlier episodes whole, not a mix of old and new files."""
    import pytest

    first = _episodes()
    d = first.save(tmp_path / "eps")

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt  # the save killed half-way through writing the steps

    monkeypatch.setattr(TensorDict, "memmap", interrupted)
    second = Episodes(first.steps[:6], torch.tensor([6]))
    with pytest.raises(KeyboardInterrupt):
        second.save(d)
    monkeypatch.undo()
    loaded = Episodes.load(d)
    assert torch.equal(loaded.episode_ends, first.episode_ends) and (loaded.steps == first.steps).all()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eps"]  # no temporary left beside it
    second.save(d)
    assert torch.equal(Episodes.load(d).episode_ends, torch.tensor([6]))


def test_saving_episodes_replaces_only_an_episode_directory_and_follows_links(tmp_path):
    import os

    import pytest

    from ddp.errors import DDPError

    eps = _episodes()
    shared = tmp_path / "data"
    shared.mkdir()
    (shared / "README.md").write_text("other work")
    with pytest.raises(DDPError, match="data: exists and is not an episode directory"):
        eps.save(shared)  # it would have replaced everything in it
    assert (shared / "README.md").read_text() == "other work"
    real = eps.save(tmp_path / "real")
    os.symlink(real, tmp_path / "link")
    smaller = Episodes(eps.steps[:6], torch.tensor([6]))
    smaller.save(tmp_path / "link")
    assert (tmp_path / "link").is_symlink()  # the link stays and reads the new episodes
    assert torch.equal(Episodes.load(tmp_path / "link").episode_ends, torch.tensor([6]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "link", "real"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert Episodes.load(eps.save(empty)).num_episodes == eps.num_episodes


def test_a_missing_episode_file_is_one_line_and_saves_reach_the_disk(tmp_path, monkeypatch):
    """An episode directory missing one leaf's file is refused (tensordict loaded it without that key: a
    KeyError at training); a save flushes every file it wrote before its rename (a power loss could leave the
    new name on files sized but never filled)."""
    import os

    import pytest

    import ddp.atomic_file
    from ddp.errors import DDPError

    flushed = []
    real_fsync = os.fsync
    monkeypatch.setattr(ddp.atomic_file.os, "fsync",
                        lambda fd: (flushed.append(os.readlink(f"/proc/self/fd/{fd}")), real_fsync(fd))[1])
    d = _episodes().save(tmp_path / "eps")
    leaves = [str(p) for p in (tmp_path / "eps").rglob("*.memmap")]
    assert leaves and all(any(f.endswith(os.path.relpath(p, tmp_path / "eps")) and ".eps.tmp-" in f
                              for f in flushed) for p in leaves)
    next((d / "steps").rglob("*.memmap")).unlink()
    with pytest.raises(DDPError, match=r"\.memmap: missing \(the episode data's"):
        Episodes.load(d)
