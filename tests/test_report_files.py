"""Files an evaluation writes (videos, contact sheets, figures): whole or not at all, and every figure that
has data to show."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

FRAMES = [np.full((16, 16, 3), v, dtype=np.uint8) for v in (0, 120, 250)]


def _failing_save(original):
    """PIL's save writing a few bytes, then failing (a full disk, a killed process)."""

    def save(self, fp, *args, **kwargs):
        if isinstance(fp, (str, Path)):
            Path(fp).write_bytes(b"GIF89a half")
        else:
            fp.write(b"half")
        raise OSError("No space left on device")

    return save


def test_a_gif_or_contact_sheet_that_fails_part_way_leaves_the_earlier_file(tmp_path, monkeypatch):
    from PIL import Image

    from ddp.video import contact_sheet, write_video

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # no mp4 writer: the GIF path
    gif = write_video(FRAMES, tmp_path / "seed0.mp4")
    sheet = contact_sheet(FRAMES, tmp_path / "seed0_sheet.png")
    assert gif.suffix == ".gif" and Image.open(gif).n_frames == 3
    before = {p.name: p.read_bytes() for p in (gif, sheet)}
    monkeypatch.setattr(Image.Image, "save", _failing_save(Image.Image.save))
    with pytest.raises(OSError, match="No space"):
        write_video(FRAMES, tmp_path / "seed0.mp4")
    with pytest.raises(OSError, match="No space"):
        contact_sheet(FRAMES, tmp_path / "seed0_sheet.png")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no half file, no temp file


def test_an_mp4_writer_that_fails_leaves_no_hidden_temp_file(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    from ddp.video import write_video

    class Broken:
        def __init__(self, path, **kwargs):
            self.path = Path(path)

        def __enter__(self):
            self.path.write_bytes(b"\x00\x00\x00 ftyp half")
            return self

        def __exit__(self, *exc):
            return False

        def append_data(self, frame):
            raise RuntimeError("ffmpeg exited")

    monkeypatch.setattr(imageio, "get_writer", Broken)
    with pytest.raises(RuntimeError, match="ffmpeg exited"):
        write_video(FRAMES, tmp_path / "seed3.mp4")
    assert list(tmp_path.iterdir()) == []


def test_odd_frame_sizes_make_a_whole_mp4(tmp_path):
    """libx264 encodes even sizes only: a 17 x 17 video was an empty file reported as written."""
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    from ddp.video import write_video

    frames = [np.full((17, 15, 3), v, dtype=np.uint8) for v in (0, 120, 250, 60, 30)]
    mp4 = write_video(frames, tmp_path / "seed0.mp4", fps=20)
    assert mp4.stat().st_size > 0
    read = imageio.mimread(mp4)
    assert len(read) == 5 and read[0].shape == (18, 16, 3)


def test_an_encoder_that_writes_nothing_is_an_error_not_an_empty_file(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    from ddp.video import write_video

    class Silent:  # ffmpeg failing inside imageio's writer, which closes without raising
        def __init__(self, path, **kwargs):
            Path(path).write_bytes(b"")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def append_data(self, frame):
            pass

    monkeypatch.setattr(imageio, "get_writer", Silent)
    with pytest.raises(RuntimeError, match="wrote nothing"):
        write_video(FRAMES, tmp_path / "seed1.mp4")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("fps", "ms"), [(20, 50), (30, 30), (25, 40), (60, 20), (1, 1000)])
def test_gif_frames_last_what_viewers_play(fps, ms, tmp_path, monkeypatch):
    """GIF durations count in 10 ms units and viewers slow anything under 20 ms to about 100 ms."""
    from PIL import Image

    from ddp.video import write_video

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    gif = write_video(FRAMES, tmp_path / "seed0.mp4", fps=fps)
    assert Image.open(gif).info["duration"] == ms


def test_a_figure_is_closed_and_its_file_kept_whole_when_saving_fails(tmp_path, monkeypatch):
    from ddp.plots import _pyplot, save_figure

    plt = _pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    path = save_figure(plt, fig, tmp_path / "success.png", dpi=50)
    good = path.read_bytes()
    assert good[:8] == b"\x89PNG\r\n\x1a\n" and not plt.get_fignums()
    fig, ax = plt.subplots()

    def fail(*args, **kwargs):
        args[0].write(b"half") if args and hasattr(args[0], "write") else Path(args[0]).write_bytes(b"half")
        raise OSError("No space left on device")

    monkeypatch.setattr(fig, "savefig", fail)
    with pytest.raises(OSError, match="No space"):
        save_figure(plt, fig, path)
    assert path.read_bytes() == good and [p.name for p in tmp_path.iterdir()] == ["success.png"]
    assert not plt.get_fignums()  # closed although the write failed


def test_a_discrepancy_trace_is_drawn_when_the_detector_statistic_is_all_nan(tmp_path):
    """A detector that records no statistic of its own (NaN scores) still has D_R-I to draw: the episode was
    dropped from the discrepancy figure because ``score or discrepancy`` picked the (non-empty) NaN list."""
    from ddp.plots import plot_report

    nan = math.nan
    episode = {"seed": 7, "success": True, "chunks": 4, "first_success_chunk": 3, "score": [nan] * 4,
               "discrepancy": [nan, 0.2, 1.5, 0.3], "mode": [0, 0, 1, 0], "disturbed": [False, True, True, True]}
    report = {"recipe": "tiny", "episodes": 1, "protocols": {"ood_ddp": {
        "success_rate": 1.0, "successes": 1, "episodes": 1, "per_episode": [episode], "detection": {}, "tau": 1.0}}}
    from matplotlib.axes import Axes

    drawn = []
    plot = Axes.plot

    def record(self, *args, **kwargs):
        drawn.append((list(args[1]) if len(args) > 1 else None, kwargs.get("label")))
        return plot(self, *args, **kwargs)

    Axes.plot = record
    try:
        paths = plot_report(report, tmp_path)
    finally:
        Axes.plot = plot
    assert tmp_path / "discrepancy_ood_ddp.png" in paths and (tmp_path / "discrepancy_ood_ddp.png").stat().st_size
    traces = [(ys, label) for ys, label in drawn if label == "$D_{R-I}$"]  # the D_R-I values, not the NaN scores
    assert len(traces) == 1 and traces[0][0][1:] == [0.2, 1.5, 0.3] and math.isnan(traces[0][0][0])


def test_a_reused_folder_keeps_only_this_reports_figures_and_results_json_lists_them(tmp_path):
    """An earlier evaluation's success.png and discrepancy_<p>.png stayed beside a report that drew none of
    them, and results.json never listed the figures it came with."""
    import json

    from ddp.detection import detection_metrics
    from ddp.eval_report import protocol_result, write_report

    episode = {"seed": 7, "success": True, "chunks": 3, "first_success_chunk": 2, "score": [0.1, 2.0, 0.2],
               "discrepancy": [0.1, 2.0, 0.2], "mode": [0, 1, 0], "disturbed": [False, True, True]}
    judged = protocol_result([episode], seconds=1.0, thresholds={"tau": 1.0},
                             detection=detection_metrics([episode]), detector={"name": "discrepancy", "tau": 1.0})
    first = {"recipe": "tiny", "episodes": 1, "protocols": {"ood_ddp": judged}}
    plots = write_report(first, tmp_path)
    assert {p.name for p in plots} == {"success.png", "discrepancy_ood_ddp.png"}
    stored = json.loads((tmp_path / "results.json").read_text())
    assert sorted(Path(p).name for p in stored["plots"]) == ["discrepancy_ood_ddp.png", "success.png"]
    robot = protocol_result([{**episode, "success": None, "score": [], "discrepancy": []}], seconds=1.0,
                            thresholds={})
    second = {"recipe": "tiny", "episodes": 1, "protocols": {"id": robot}}
    assert write_report(second, tmp_path) == []
    assert not list(tmp_path.glob("*.png")) and json.loads((tmp_path / "results.json").read_text())["plots"] == []
