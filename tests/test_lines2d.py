"""2D line detection, import and the lines2d.h5 cache."""
import json
import logging

import h5py
import numpy as np
import pytest

from lipmap import logger
from lipmap.errors import InputError
from lipmap.imageio import write_color
from lipmap.lines2d import (
    LineDetectorConfig,
    detect_lines,
    detect_lines_image,
    filter_lines,
    get_conf,
    import_lines,
    list_names,
    load_lines,
    read_lines_array,
    read_wireframe_json,
)
from lipmap.scene import Camera, View


@pytest.fixture
def records():
    """Log records of the lipmap logger (it does not propagate to the root, so caplog misses it)."""
    out = []

    class H(logging.Handler):
        def emit(self, record):
            out.append(record)

    h = H(level=logging.WARNING)
    logger.addHandler(h)
    yield out
    logger.removeHandler(h)


def edge_image():
    img = np.zeros((200, 300), np.uint8)
    img[:, 100:] = 255  # columns 0..99 dark: the edge is at x = 100 in COLMAP convention
    return img


def box_image(w=160, h=120):
    img = np.full((h, w, 3), 30, np.uint8)
    img[30:90, 40:120] = 220
    return img


class TestDetect:
    def test_pixel_convention_pin(self):
        lines, scores = detect_lines_image(edge_image())
        assert lines.shape == (1, 4) and scores.shape == (1,)
        # OpenCV would say 99.4 (integer pixel centres); COLMAP convention puts the edge at 100
        assert abs(lines[0, 0] - 100.0) < 0.25 and abs(lines[0, 2] - 100.0) < 0.25
        assert abs(abs(lines[0, 3] - lines[0, 1]) - 197.5) < 2.0

    def test_min_length_scales_with_image(self):
        c = LineDetectorConfig(min_length=15)
        assert c.min_length_for(640, 480) == pytest.approx(15)
        assert c.min_length_for(1280, 960) == pytest.approx(30)

    def test_filter_sorts_and_caps(self):
        lines = np.array([[0, 0, 10, 0], [0, 0, 30, 0], [0, 0, 3, 0], [0, 0, 20, 0]], float)
        out, sc = filter_lines(lines, np.arange(4.0), min_length=5, max_lines=2)
        np.testing.assert_array_equal(out[:, 2], [30, 20])
        np.testing.assert_array_equal(sc, [1, 3])

    def test_presets(self):
        assert get_conf("lsd-fast").refine == "std"
        assert get_conf({"preset": "lsd", "max_lines": 7}).max_lines == 7
        with pytest.raises(InputError):
            get_conf("nope")

    def test_blank_image_gives_empty(self):
        lines, scores = detect_lines_image(np.zeros((50, 60), np.uint8))
        assert lines.shape == (0, 4) and scores.shape == (0,)


class TestCache:
    def test_detect_write_skip_overwrite(self, tmp_path, records):
        cam = Camera(160, 120, (100, 100, 80, 60))
        views = []
        for i, img in enumerate([box_image(), np.zeros((120, 160, 3), np.uint8)]):
            p = tmp_path / "seq-01" / f"frame-{i:06d}.color.png"
            write_color(p, img)
            views.append(View(f"seq-01/frame-{i:06d}.color.png", cam, np.eye(4), p))
        out = detect_lines(views, tmp_path / "lines2d.h5", "lsd")
        assert list_names(out) == ["seq-01/frame-000000.color.png", "seq-01/frame-000001.color.png"]
        l0, s0 = load_lines(out, views[0].name, with_scores=True)
        assert l0.dtype == np.float32 and l0.shape[1] == 4 and len(l0) >= 4 and len(s0) == len(l0)
        # the box edges, in COLMAP convention: x = 40 / 120, y = 30 / 90
        xs = np.concatenate([l0[:, 0], l0[:, 2]])
        assert np.min(np.abs(xs - 40.0)) < 0.5 and np.min(np.abs(xs - 120.0)) < 0.5
        assert load_lines(out, views[1].name).shape == (0, 4)
        assert any("No lines" in r.getMessage() for r in records)
        with h5py.File(out) as f:
            assert f.attrs["detector"] == "lsd"
            assert json.loads(f.attrs["conf"])["min_length"] == 15.0
            assert "seq-01" in f and isinstance(f["seq-01"], h5py.Group)
            assert f[views[0].name]["lines"].shape[1] == 4
        # a second run skips everything (the file content stays the same)
        before = out.read_bytes()
        detect_lines(views, out, "lsd")
        assert out.read_bytes() == before
        # other settings without overwrite: refuse to mix
        with pytest.raises(InputError):
            detect_lines(views, out, "lsd-long")
        detect_lines(views, out, "lsd-long", overwrite=True)
        with h5py.File(out) as f:
            assert json.loads(f.attrs["conf"])["min_length"] == 30.0

    def test_paths_and_missing_name(self, tmp_path):
        p = tmp_path / "a.png"
        write_color(p, box_image())
        out = detect_lines([p], tmp_path / "l.h5")
        assert list_names(out) == ["a.png"]
        with pytest.raises(InputError):
            load_lines(out, "b.png")
        with pytest.raises(InputError):
            load_lines(tmp_path / "missing.h5", "a.png")


def test_lsd_on_real_frame(redkitchen_root, tmp_path):
    from lipmap.imageio import read_color

    img = read_color(redkitchen_root / "redkitchen" / "seq-01" / "frame-000000.color.jpg", gray=True)
    lines, scores = detect_lines_image(img)
    assert len(lines) > 100
    assert np.all(np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1]) >= 15.0)
    assert (lines[:, [0, 2]] >= 0).all() and (lines[:, [0, 2]] <= 640).all()


class TestImport:
    def wireframe(self, path, w=320, h=240):
        data = {
            "vertices": [[10.0, 20.0], [110.0, 20.0], [110.0, 70.0]],
            "vertices-score": [0.9, 0.8, 0.7],
            "edges": [[0, 1], [1, 2]],
            "edges-weights": [0.99, 0.5],
            "height": h,
            "width": w,
        }
        path.write_text(json.dumps(data))
        return path

    def test_wireframe_rescale(self, tmp_path):
        f = self.wireframe(tmp_path / "a.json")
        lines, scores = read_wireframe_json(f, image_size=(640, 480))
        np.testing.assert_allclose(lines, [[20, 40, 220, 40], [220, 40, 220, 140]])
        np.testing.assert_allclose(scores, [0.99, 0.5])
        lines, _ = read_wireframe_json(f, image_size=(320, 480), min_score=0.9, pixel_offset=0.5)
        np.testing.assert_allclose(lines, [[10.5, 40.5, 110.5, 40.5]])

    def test_wireframe_bad(self, tmp_path):
        bad = tmp_path / "bad.json"
        bad.write_text('{"vertices": [[0, 0]], "edges": [[0, 3]], "edges-weights": [1.0]}')
        with pytest.raises(InputError, match="bad.json"):
            read_wireframe_json(bad)
        bad.write_text("{not json")
        with pytest.raises(InputError, match="bad.json"):
            read_wireframe_json(bad)

    def test_arrays(self, tmp_path):
        L = np.array([[1.0, 2.0, 30.0, 4.0], [5.0, 6.0, 7.0, 80.0]])
        np.savez(tmp_path / "a.npz", lines=L, scores=np.array([0.3, 0.7]))
        np.savez(tmp_path / "b.npz", L)
        l, s = read_lines_array(tmp_path / "a.npz")
        np.testing.assert_allclose(l, L)
        np.testing.assert_allclose(s, [0.3, 0.7])
        l, s = read_lines_array(tmp_path / "b.npz", pixel_offset=0.5)
        np.testing.assert_allclose(l, L + 0.5)
        with h5py.File(tmp_path / "c.h5", "w") as f:
            f["seq-01/x.png"] = L
        l, _ = read_lines_array(tmp_path / "c.h5", "seq-01/x.png")
        np.testing.assert_allclose(l, L)
        (tmp_path / "d.txt").write_text("2\n1 2 30 4\n5 6 7 80\n")
        np.testing.assert_allclose(read_lines_array(tmp_path / "d.txt")[0], L)
        np.save(tmp_path / "e.npy", np.zeros((3, 3)))
        with pytest.raises(InputError, match="e.npy"):
            read_lines_array(tmp_path / "e.npy")

    def test_import_folder(self, tmp_path):
        cam = Camera(640, 480, (500, 500, 320, 240))
        src = tmp_path / "wf"
        (src / "seq-01").mkdir(parents=True)
        self.wireframe(src / "seq-01" / "frame-000000.color.json")
        np.savez(src / "seq-01" / "frame-000001.color.npz", lines=np.zeros((0, 4)))
        views = [View(f"seq-01/frame-00000{i}.color.png", cam, np.eye(4), tmp_path / "x") for i in range(2)]
        out = import_lines(views, src, tmp_path / "lines2d.h5")
        np.testing.assert_allclose(load_lines(out, views[0].name), [[20, 40, 220, 40], [220, 40, 220, 140]])
        assert load_lines(out, views[1].name).shape == (0, 4)
        views.append(View("seq-01/frame-000009.color.png", cam, np.eye(4), tmp_path / "x"))
        with pytest.raises(InputError, match="frame-000009"):
            import_lines(views, src, tmp_path / "lines2d.h5")

    def test_import_h5(self, tmp_path):
        L = np.array([[1.0, 2.0, 30.0, 4.0]])
        with h5py.File(tmp_path / "ext.h5", "w") as f:
            f.create_group("a/b.png").create_dataset("lines", data=L)
        out = import_lines(["a/b.png"], tmp_path / "ext.h5", tmp_path / "lines2d.h5", pixel_offset=0.5)
        np.testing.assert_allclose(load_lines(out, "a/b.png"), L + 0.5)
