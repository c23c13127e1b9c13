"""Mapping metrics M1 / M2 on known answers."""
import json

import numpy as np
import pytest
import trimesh
from trimesh.triangles import closest_point

from lipmap.errors import InputError
from lipmap.evaluation import (
    EvalConfig,
    evaluate_linemap,
    gt_from_depth,
    load_ground_truth,
    m2_metrics,
    main,
    voxel_downsample,
    write_points_ply,
)
from lipmap.imageio import write_depth
from lipmap.linemap import LineMap
from lipmap.scene import Camera, View

BOX = trimesh.creation.box(extents=(2.0, 3.0, 1.5))  # centred at the origin


def box_edges(mesh=BOX):
    v = mesh.vertices
    edges = mesh.edges_unique
    # keep the 12 box edges (drop face diagonals): their endpoints differ in exactly one coordinate
    keep = (np.abs(v[edges[:, 0]] - v[edges[:, 1]]) > 1e-9).sum(1) == 1
    return v[edges[keep]]


def top_face_lines(offset=0.0):
    """Lines lying on the top face z = 0.75 (inside it), raised by ``offset`` along the normal."""
    z = 0.75 + offset
    return np.array(
        [[[-0.8, -1.2, z], [0.7, -1.2, z]], [[-0.5, -1.0, z], [-0.5, 1.3, z]], [[0.0, 0.0, z], [0.6, 0.9, z]]]
    )


class TestMeshGT:
    def test_lines_on_edges(self):
        lines = box_edges()
        assert len(lines) == 12
        res = evaluate_linemap(lines, BOX, m1_thresholds=(0.05,), gt_points_per_m2=2000)
        m1 = res["M1"]["line"]
        assert m1["prec@0.05"] == 1.0 and m1["acc"] < 1e-9
        assert res["M1"]["junction"]["prec@0.05"] == 1.0
        total = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1).sum()
        assert total == pytest.approx(4 * (2 + 3 + 1.5))
        for t in (5, 10, 50):
            assert res["M2"][f"R@{t}mm"] == pytest.approx(total)
            assert res["M2"][f"P@{t}mm"] == 100.0
        assert res["n_lines"] == 12 and res["gt"]["kind"] == "mesh"
        # edges cover only a sliver of the surface: recall is low, COMP large (ACC/COMP not swapped)
        assert m1["recall@0.05"] < 0.2 and m1["comp"] > 0.3

    def test_offset_3cm(self):
        res = evaluate_linemap(top_face_lines(0.03), BOX, m1_thresholds=(0.02, 0.05), gt_points_per_m2=2000)
        m1 = res["M1"]["line"]
        assert m1["prec@0.05"] == 1.0 and m1["prec@0.02"] == 0.0
        assert m1["acc"] == pytest.approx(0.03, abs=1e-9)
        assert res["M2"]["R@5mm"] == 0.0 and res["M2"]["P@10mm"] == 0.0
        total = np.linalg.norm(np.diff(top_face_lines(), axis=1)[:, 0], axis=1).sum()
        assert res["M2"]["R@50mm"] == pytest.approx(total) and res["M2"]["P@50mm"] == 100.0

    def test_partial_line_ratio(self):
        # a line leaving the box top: half of it is within 5 mm, the other half rises 0 -> 0.5 m
        line = np.array([[[-0.5, 0.0, 0.75], [0.5, 0.0, 0.75]], [[0.5, 0.0, 0.75], [1.0, 0.0, 1.25]]])
        r = m2_metrics(line, load_ground_truth(BOX, EvalConfig(gt_points_per_m2=1000)), (5,), 1000)
        # line 0 fully in (1 m); line 1 within 5 mm for its first 0.005 / 0.5 fraction (plus one sample)
        seg2 = np.sqrt(0.5)
        assert r["R@5mm"] == pytest.approx(1.0 + seg2 * 0.0105, abs=2e-3)
        assert r["P@5mm"] == 100.0

    def test_exact_distance_against_brute_force(self):
        m = trimesh.creation.icosphere(subdivisions=3)
        rng = np.random.default_rng(0)
        q = rng.normal(size=(200, 3))
        q = q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0.9, 1.1, (200, 1))
        F = len(m.faces)
        cp = closest_point(np.repeat(m.triangles[None], len(q), 0).reshape(-1, 3, 3), np.repeat(q, F, 0))
        ref = np.linalg.norm(cp - np.repeat(q, F, 0), axis=1).reshape(len(q), F).min(1)
        d = load_ground_truth(m).distance(q)
        assert np.abs(d - ref).max() < 1e-4
        assert np.mean(np.abs(d - ref) < 1e-9) > 0.98
        d_up = load_ground_truth(m).distance(q, upper=0.03)
        np.testing.assert_allclose(d_up[ref <= 0.029], d[ref <= 0.029])
        assert np.isinf(d_up[ref > 0.031]).all()


class TestPointGT:
    def test_acc_comp_not_swapped(self):
        gt = np.stack([np.linspace(0, 1, 1001), np.zeros(1001), np.zeros(1001)], 1)
        pred = np.array([[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]])
        res = evaluate_linemap(pred, gt, m1_thresholds=(0.05,))
        m1 = res["M1"]["line"]
        pts = np.stack([np.linspace(0, 0.5, 100), np.zeros(100), np.zeros(100)], 1)
        d_gt = np.abs(gt[:, None, 0] - pts[None, :, 0]).min(1)  # brute force
        assert m1["acc"] < 5e-4 and m1["prec@0.05"] == 1.0  # GT spacing 1 mm
        assert m1["comp"] == pytest.approx(d_gt.mean())
        assert m1["recall@0.05"] == pytest.approx(np.mean(d_gt <= 0.05))
        assert m1["recall@0.05"] == pytest.approx(551 / 1001, abs=2e-3)
        p, r = 1.0, m1["recall@0.05"]
        assert m1["f@0.05"] == pytest.approx(2 * p * r / (p + r))

    def test_offset_on_dense_cloud(self, tmp_path):
        xs, ys = np.meshgrid(np.arange(-1, 1, 0.004), np.arange(-1.5, 1.5, 0.004))
        gt = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.75)], 1)
        path = write_points_ply(tmp_path / "gt.ply", gt)
        res = evaluate_linemap(top_face_lines(0.03), path, m1_thresholds=(0.02, 0.05))
        assert res["gt"]["kind"] == "points" and res["gt"]["n_points"] == len(gt)
        m1 = res["M1"]["line"]
        assert m1["prec@0.05"] == 1.0 and m1["prec@0.02"] == 0.0
        assert m1["acc"] == pytest.approx(0.03, abs=5e-4)

    def test_supports_and_file_step(self, tmp_path):
        lines = top_face_lines()
        tracks = [[("a", 0, np.zeros(4))], [("a", 1, np.zeros(4)), ("b", 2, np.zeros(4))], [("a", 2, np.zeros(4))] * 3]
        lm = LineMap(lines, tracks)
        lm.save(tmp_path / "linemap.h5")
        out = main(tmp_path / "linemap.h5", BOX, tmp_path / "metrics.json", conf="fast")
        res = json.loads(out.read_text())
        assert res["M2"]["supports_images"] == pytest.approx(4 / 3)
        assert res["M2"]["supports_lines"] == pytest.approx(2.0)
        assert res["M2"]["supports_images_median"] == 1.0  # images per line: 1, 2, 1
        assert res["M1"]["line"]["prec@0.05"] == 1.0

    def test_empty(self):
        res = evaluate_linemap(np.zeros((0, 2, 3)), np.zeros((5, 3)))
        assert res["n_lines"] == 0 and res["M2"]["R@5mm"] == 0.0 and res["M1"]["line"]["recall@0.05"] == 0.0

    def test_bad_gt(self, tmp_path):
        with pytest.raises(InputError):
            evaluate_linemap(top_face_lines(), tmp_path / "missing.ply")
        (tmp_path / "bad.npy").write_bytes(b"nonsense")
        with pytest.raises((InputError, ValueError)):
            evaluate_linemap(top_face_lines(), tmp_path / "bad.npy")


def test_voxel_downsample():
    pts = np.array([[0.001, 0.001, 0.001], [0.003, 0.005, 0.007], [0.015, 0.0, 0.0], [-0.001, 0.0, 0.0]])
    out = voxel_downsample(pts, 0.01)
    assert len(out) == 3
    assert any(np.allclose(o, [0.002, 0.003, 0.004]) for o in out)


def test_gt_from_depth(tmp_path):
    cam = Camera(64, 48, (50.0, 50.0, 32.0, 24.0))
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, :5] = 0  # invalid strip
    views = []
    for i, tx in enumerate((0.0, -0.1)):  # second camera 10 cm to the right (cam_from_world t = -c)
        p = tmp_path / f"d{i}.png"
        write_depth(p, depth)
        T = np.eye(4)
        T[0, 3] = tx
        views.append(View(f"v{i}", cam, T, tmp_path / "c.png", depth_path=p))
    pts = gt_from_depth(views, voxel=0.02)
    assert np.allclose(pts[:, 2], 2.0, atol=1e-6)
    # the second view extends the first one's footprint to the right by 0.1 m
    x1 = (64 - 32) / 50 * 2.0
    assert pts[:, 0].max() == pytest.approx(x1 + 0.1, abs=0.03)
    assert pts[:, 0].min() == pytest.approx((5 - 32) / 50 * 2.0, abs=0.03)
    assert len(pts) == len(voxel_downsample(pts, 0.02))


def test_m2_lipschitz_shortcut_is_exact():
    from lipmap.geometry import sample_segments

    rng = np.random.default_rng(5)
    gt_pts, _ = trimesh.sample.sample_surface(BOX, 50_000, seed=0)
    a, _ = trimesh.sample.sample_surface(BOX, 300, seed=1)
    lines = np.stack([a, a + rng.normal(scale=0.3, size=(300, 3))], 1)
    gt = load_ground_truth(gt_pts)
    res = m2_metrics(lines, gt, (5, 10, 50), 1000)
    d = gt.distance(sample_segments(lines, 1000).reshape(-1, 3)).reshape(300, 1000)
    L = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    for t in (5, 10, 50):
        ratio = (d <= t / 1000).mean(1)
        assert res[f"R@{t}mm"] == pytest.approx((L * ratio).sum(), rel=1e-12)
        assert res[f"P@{t}mm"] == pytest.approx(100 * np.mean(ratio > 0))


def test_cli_map_eval(tmp_path, capsys):
    """``lipmap-loc map-eval`` on a linemap.h5 and on its LIMAP export, with custom thresholds."""
    from localization.cli import main

    lm = LineMap(top_face_lines(), [[("a.png", i, np.zeros(4))] for i in range(3)])
    lm.save(tmp_path / "linemap.h5")
    lm.to_limap(tmp_path / "limap")
    BOX.export(tmp_path / "box.ply")
    for src, out in ((tmp_path / "linemap.h5", "m.json"), (tmp_path / "limap", "l.json")):
        assert main(["map-eval", "--linemap", str(src), "--gt", str(tmp_path / "box.ply"),
                     "--thresholds", "0.01,0.05", "--json", str(tmp_path / out)]) == 0
        res = json.loads((tmp_path / out).read_text())
        assert res["gt"]["kind"] == "mesh" and res["M1"]["line"]["prec@0.01"] == 1.0 and res["n_lines"] == 3
    assert main(["map-eval", "--linemap", str(tmp_path / "linemap.h5")]) == 2
    assert main(["map-eval", "--linemap", str(tmp_path / "linemap.h5"), "--gt", str(tmp_path / "box.ply"),
                 "--thresholds", "5cm"]) == 2
    err = capsys.readouterr().err
    assert "--gt" in err and "5cm" in err


def test_scene_ground_truth_prefers_the_mesh():
    from types import SimpleNamespace

    from lipmap.evaluation import scene_ground_truth

    assert scene_ground_truth(SimpleNamespace(gt_mesh="mesh.ply", mapping=[], query=[])) == "mesh.ply"


def test_cli_map_eval_min_support(tmp_path, capsys):
    """``--min-support N`` scores only the lines seen in >= N images (LIMAP's n_visible_views)."""
    from localization.cli import main

    tracks = [[("a.png", 0, np.zeros(4)), ("b.png", 3, np.zeros(4))], [("a.png", 1, np.zeros(4))],
              [("a.png", 2, np.zeros(4)), ("a.png", 4, np.zeros(4))]]  # 2 images; 1; 1 image twice
    LineMap(top_face_lines(), tracks).save(tmp_path / "linemap.h5")
    BOX.export(tmp_path / "box.ply")
    args = ["map-eval", "--linemap", str(tmp_path / "linemap.h5"), "--gt", str(tmp_path / "box.ply")]
    assert main([*args, "--min-support", "2", "--json", str(tmp_path / "m.json")]) == 0
    res = json.loads((tmp_path / "m.json").read_text())
    assert res["n_lines"] == 1 and res["min_support"] == 2
    assert "1 of 3 lines are seen in >= 2 images" in capsys.readouterr().out
    assert main([*args, "--min-support", "3", "--json", str(tmp_path / "e.json")]) == 0  # no line left
    assert json.loads((tmp_path / "e.json").read_text())["n_lines"] == 0
    LineMap(top_face_lines(), [tracks[0], [], tracks[2]]).save(tmp_path / "linemap.h5")  # no image verifies line 1
    assert main([*args, "--min-support", "1", "--json", str(tmp_path / "v.json")]) == 0
    assert json.loads((tmp_path / "v.json").read_text())["n_lines"] == 2
    assert main([*args, "--json", str(tmp_path / "all.json")]) == 0  # default 0: every line
    assert json.loads((tmp_path / "all.json").read_text())["n_lines"] == 3
    assert main([*args, "--min-support", "-1"]) == 2
    assert "argument --min-support: must be an integer >= 0" in capsys.readouterr().err
