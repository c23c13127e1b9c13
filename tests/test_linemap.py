"""LineMap: HDF5 round trip, PLY, LIMAP export/import (layout pinned to LIMAP's LineTrack::Write)."""
import time

import h5py
import numpy as np
import pytest

from lipmap.errors import InputError
from lipmap.linemap import LineMap, Observation, read_ply_lines


def make_map(n=3, seed=0):
    rng = np.random.default_rng(seed)
    lines = rng.normal(size=(n, 2, 3))
    names = ["seq-01/frame-000000.color.png", "seq-01/frame-000010.color.png", "seq-02/frame-000005.color.png"]
    tracks = []
    for i in range(n):
        k = i % 3 + 1
        tracks.append([(names[j % 3], int(rng.integers(0, 500)), rng.uniform(0, 640, 4)) for j in range(k)])
    if n >= 3:  # one image seen twice in a track: n_images < n_lines
        tracks[2].append((names[0], 7, np.array([1.5, 2.25, 3.0, 4.125])))
    planes = {"center": rng.normal(size=(4, 3)), "rotation": rng.normal(size=(4, 4)), "radii": rng.uniform(size=(4, 4))}
    return LineMap(lines, tracks, planes=planes, metadata={"method": "test", "config": {"a": 1}})


def assert_same(a: LineMap, b: LineMap, exact=True):
    assert len(a) == len(b)
    np.testing.assert_array_equal(a.lines, b.lines) if exact else np.testing.assert_allclose(a.lines, b.lines)
    for ta, tb in zip(a.tracks, b.tracks):
        assert [(o.image_name, o.line2d_index) for o in ta] == [(o.image_name, o.line2d_index) for o in tb]
        for oa, ob in zip(ta, tb):
            np.testing.assert_array_equal(oa.segment, ob.segment)
    np.testing.assert_array_equal(a.supports, b.supports)


class TestLineMap:
    def test_supports_from_tracks(self):
        m = make_map()
        np.testing.assert_array_equal(m.supports, [[1, 1], [2, 2], [3, 4]])
        assert isinstance(m.tracks[0][0], Observation)
        assert m.image_names()[0] == "seq-01/frame-000000.color.png"

    def test_bad_shapes(self):
        with pytest.raises(InputError):
            LineMap(np.zeros((3, 3)))
        with pytest.raises(InputError):
            LineMap(np.zeros((2, 2, 3)), tracks=[[]])

    def test_subset(self):
        m = make_map(5)
        s = m.subset(np.array([False, True, False, True, False]))
        assert len(s) == 2
        np.testing.assert_array_equal(s.lines[1], m.lines[3])
        assert [(o.image_name, o.line2d_index) for o in s.tracks[1]] == [(o.image_name, o.line2d_index) for o in m.tracks[3]]
        np.testing.assert_array_equal(s.supports, m.supports[[1, 3]])

    def test_h5_round_trip(self, tmp_path):
        m = make_map(6)
        p = m.save(tmp_path / "linemap.h5")
        r = LineMap.load(p)
        assert_same(m, r)
        assert r.metadata == {"method": "test", "config": {"a": 1}}
        for k in ("center", "rotation", "radii"):
            np.testing.assert_array_equal(r.planes[k], m.planes[k])
        with h5py.File(p) as f:  # flat layout, not one group per track
            assert set(f["tracks"].keys()) == {"offsets", "image_index", "image_names", "line_index", "segments"}
            assert f["tracks/offsets"][-1] == sum(len(t) for t in m.tracks)

    def test_empty_round_trip(self, tmp_path):
        m = LineMap(np.zeros((0, 2, 3)))
        r = LineMap.load(m.save(tmp_path / "e.h5"))
        assert len(r) == 0 and r.planes is None
        assert len(LineMap.from_limap(r.to_limap(tmp_path / "lim"))) == 0

    def test_load_errors(self, tmp_path):
        with pytest.raises(InputError, match="missing"):
            LineMap.load(tmp_path / "nope.h5")
        with h5py.File(tmp_path / "x.h5", "w") as f:
            f["lines"] = np.zeros((1, 2, 3))
        with pytest.raises(InputError, match="x.h5"):
            LineMap.load(tmp_path / "x.h5")
        p = make_map().save(tmp_path / "y.h5")
        with h5py.File(p, "a") as f:
            f["tracks/offsets"][-1] = 99
        with pytest.raises(InputError, match="offsets"):
            LineMap.load(p)

    def test_many_tracks_fast(self, tmp_path):
        rng = np.random.default_rng(0)
        n = 5000
        names = [f"seq-01/frame-{i:06d}.color.png" for i in range(100)]
        tracks = [[(names[j], j, rng.uniform(0, 640, 4)) for j in rng.choice(100, 8, replace=False)] for _ in range(n)]
        m = LineMap(rng.normal(size=(n, 2, 3)), tracks)
        t0 = time.perf_counter()
        r = LineMap.load(m.save(tmp_path / "big.h5"))
        assert time.perf_counter() - t0 < 5.0
        assert r.supports[:, 1].sum() == 8 * n


class TestPly:
    @pytest.mark.parametrize("binary", [True, False])
    def test_round_trip(self, tmp_path, binary):
        m = make_map(4)
        p = m.to_ply(tmp_path / "l.ply", binary=binary)
        head = p.read_bytes()[:400]
        assert b"element vertex 8" in head and b"element edge 4" in head and b"property int vertex1" in head
        np.testing.assert_allclose(read_ply_lines(p), m.lines, atol=1e-6)

    def test_independent_reader(self, tmp_path):
        import trimesh

        m = make_map(4)
        path = trimesh.load(m.to_ply(tmp_path / "l.ply"))
        assert isinstance(path, trimesh.path.Path3D) and len(path.entities) == 4
        segs = np.array([path.vertices[e.points] for e in path.entities])
        np.testing.assert_allclose(segs, m.lines, atol=1e-6)


class TestLimap:
    def test_layout_pin(self, tmp_path):
        line = np.array([[[0.5, -1.0, 2.0], [1.5, 0.25, 3.0]]])
        track = [[("b.png", 3, [1.0, 2.0, 3.0, 4.0]), ("a.png", 5, [5.5, 6.0, 7.0, 8.0]), ("b.png", 9, [0, 0, 1, 1])]]
        out = LineMap(line, track).to_limap(tmp_path / "lim")
        assert out.name == "finaltracks"
        text = (out / "track_0.txt").read_text().splitlines()
        assert text[0].split() == ["0.5", "-1.0", "2.0", "1.5", "0.25", "3.0"]
        assert text[1] == "3 2"
        assert text[2].split() == ["image_id_list", "1", "0", "1"]  # ids from the sorted names: a=0, b=1
        assert text[3].split() == ["line_id_list", "3", "5", "9"]
        assert text[4] == "line2d_list"
        assert [float(x) for x in text[5].split()] == [1.0, 2.0, 3.0, 4.0]
        assert text[8] == "END" and len(text) == 9
        assert (tmp_path / "lim" / "image_list.txt").read_text() == "number of images, 2\na.png\nb.png\n"

    def test_round_trip(self, tmp_path):
        m = make_map(7, seed=3)
        m.to_limap(tmp_path / "lim")
        r = LineMap.from_limap(tmp_path / "lim")
        assert_same(m, r)
        r2 = LineMap.from_limap(tmp_path / "lim" / "finaltracks")  # image_list.txt found in the parent
        assert_same(m, r2)

    def test_explicit_image_names(self, tmp_path):
        m = make_map(3)
        names = ["seq-02/frame-000005.color.png", "zzz.png", "seq-01/frame-000010.color.png",
                 "seq-01/frame-000000.color.png"]
        m.to_limap(tmp_path / "lim", image_names=names)
        assert (tmp_path / "lim/finaltracks/track_0.txt").read_text().splitlines()[2].split()[1] == "3"
        assert_same(m, LineMap.from_limap(tmp_path / "lim"))
        with pytest.raises(InputError):
            m.to_limap(tmp_path / "lim2", image_names=["zzz.png"])

    def test_reads_limap_written_file(self, tmp_path):
        # as LIMAP's LineTrack::Write prints it: fixed 10 decimals, trailing spaces, auxiliary blocks
        d = tmp_path / "finaltracks"
        d.mkdir()
        (d / "track_0.txt").write_text(
            "0.1000000000 0.2000000000 0.3000000000 1.0000000000 2.0000000000 3.0000000000 \n"
            "2 2\n"
            "image_id_list 4 7 \n"
            "line_id_list 10 11 \n"
            "line2d_list\n"
            "1.0000000000 2.0000000000 3.0000000000 4.0000000000 \n"
            "5.0000000000 6.0000000000 7.0000000000 8.0000000000 \n"
            "node_id_list 0 1 \n"
            "score_list 0.5000000000 0.2500000000 \n"
            "line3d_list\n"
            "0 0 0 1 1 1 \n"
            "0 0 0 1 1 1 \n"
            "END\n"
        )
        m = LineMap.from_limap(tmp_path, image_list={4: "x.png", 7: "y.png"})
        np.testing.assert_allclose(m.lines[0], [[0.1, 0.2, 0.3], [1, 2, 3]])
        assert [(o.image_name, o.line2d_index) for o in m.tracks[0]] == [("x.png", 10), ("y.png", 11)]
        np.testing.assert_array_equal(m.tracks[0][1].segment, [5, 6, 7, 8])
        names_by_id = LineMap.from_limap(tmp_path)
        assert names_by_id.tracks[0][0].image_name == "4"

    @pytest.mark.parametrize(
        "text,line_no",
        [
            ("0 0 0 1 1\n1 1\nimage_id_list 0\nline_id_list 0\nline2d_list\n0 0 1 1\nEND\n", 1),
            ("0 0 0 1 1 1\n2 1\nimage_id_list 0\nline_id_list 0 1\nline2d_list\n0 0 1 1\n0 0 1 1\nEND\n", 3),
            ("0 0 0 1 1 1\n1 1\nimage_ids 0\nline_id_list 0\nline2d_list\n0 0 1 1\nEND\n", 3),
            ("0 0 0 1 1 1\n1 1\nimage_id_list 0\nline_id_list 0\nline2d_list\n0 0 x 1\nEND\n", 6),
            ("0 0 0 1 1 1\n2 2\nimage_id_list 0 0\nline_id_list 0 1\nline2d_list\n0 0 1 1\n0 0 1 1\nEND\n", 3),
            ("0 0 0 1 1 1\n1 1\nimage_id_list 0\nline_id_list 0\nline2d_list\n", 6),
            ("0 0 0 1 1 1\n1 1\nimage_id_list 0\nline_id_list 0\nline2d_list\n0 0 1 1\ngarbage\nEND\n", 7),
        ],
    )
    def test_malformed(self, tmp_path, text, line_no):
        d = tmp_path / "finaltracks"
        d.mkdir()
        (d / "track_0.txt").write_text(text)
        with pytest.raises(InputError, match=rf"track_0\.txt: line {line_no}:"):
            LineMap.from_limap(d, image_list=["a.png"])

    def test_unknown_image_id_and_gaps(self, tmp_path):
        d = tmp_path / "finaltracks"
        d.mkdir()
        (d / "track_0.txt").write_text("0 0 0 1 1 1\n1 1\nimage_id_list 3\nline_id_list 0\nline2d_list\n0 0 1 1\nEND\n")
        with pytest.raises(InputError, match="image id 3"):
            LineMap.from_limap(d, image_list=["a.png"])
        (d / "track_2.txt").write_text("")
        with pytest.raises(InputError, match="gaps"):
            LineMap.from_limap(d, image_list=["a.png"])


def test_cli_export(tmp_path):
    import argparse

    from lipmap.linemap import add_linemap_export_parser

    parser = argparse.ArgumentParser()
    add_linemap_export_parser(parser.add_subparsers())
    m = make_map(4)
    m.save(tmp_path / "linemap.h5")
    args = parser.parse_args(["linemap-export", str(tmp_path / "linemap.h5"), "--ply", str(tmp_path / "l.ply"),
                              "--limap", str(tmp_path / "lim")])
    args.func(args)
    np.testing.assert_allclose(read_ply_lines(tmp_path / "l.ply"), m.lines, atol=1e-6)
    args = parser.parse_args(["linemap-export", str(tmp_path / "lim"), "--h5", str(tmp_path / "back.h5")])
    args.func(args)
    assert_same(m, LineMap.load(tmp_path / "back.h5"))
    with pytest.raises(InputError):
        args = parser.parse_args(["linemap-export", str(tmp_path / "linemap.h5")])
        args.func(args)


def test_subset_renumbers_edge_line():
    from lipmap.linemap import LineMap

    lines = np.arange(3 * 6, dtype=float).reshape(3, 2, 3)
    planes = {"corners": np.zeros((2, 4, 3)), "edge_line": np.array([[0, 1, -1, 2], [2, -1, -1, -1]])}
    sub = LineMap(lines, planes=planes).subset([2, 0])
    np.testing.assert_array_equal(sub.planes["edge_line"], [[1, -1, -1, 0], [0, -1, -1, -1]])
    np.testing.assert_array_equal(sub.lines[0], lines[2])
