"""Baseline lift: back-projection of 2D lines with depth, on a ray-cast synthetic scene and real data."""
import numpy as np
import pytest
import trimesh

from lipmap.evaluation import evaluate_linemap, gt_from_depth
from lipmap.geometry import clip_segments_to_image, point_line_distance, project_points, project_segments
from lipmap.imageio import write_depth
from lipmap.lift import LiftConfig, lift_linemap, lift_view_lines, main
from lipmap.linemap import LineMap
from lipmap.lines2d import detect_lines, import_lines
from lipmap.poses import invert_T, make_T
from lipmap.scene import Camera, View

CAM = Camera(320, 240, (280.0, 280.0, 160.0, 120.0))
CUBE = trimesh.creation.box(extents=(1, 1, 1))
CUBE.apply_translation([0, 0, 4])
WALL = trimesh.creation.box(extents=(10, 10, 0.1))
WALL.apply_translation([0, 0, 6])
SCENE = trimesh.util.concatenate([CUBE, WALL])


def lookat(c, target, up=(0, -1, 0)):
    c = np.asarray(c, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return make_T(R, -R @ c)


def render_depth(T):
    rays = CAM.pixel_rays().reshape(-1, 3)
    Tw = invert_T(T)
    dirs = rays @ Tw[:3, :3].T
    loc, ri, _ = SCENE.ray.intersects_location(np.repeat(Tw[:3, 3][None], len(dirs), 0), dirs, multiple_hits=False)
    depth = np.zeros(len(dirs))
    depth[ri] = ((loc - Tw[:3, 3]) @ T[:3, :3].T)[:, 2]
    return depth.reshape(CAM.height, CAM.width).astype(np.float32)


def cube_edges():
    v, e = CUBE.vertices, CUBE.edges_unique
    keep = (np.abs(v[e[:, 0]] - v[e[:, 1]]) > 1e-9).sum(1) == 1
    return v[e[keep]]


def visible_edges_2d(T, depth):
    """Projections of the cube edges whose midpoint is visible (rendered depth = true depth)."""
    E = cube_edges()
    p, valid = project_segments(E, T, CAM)
    segs, inside = clip_segments_to_image(p, CAM.width, CAM.height)
    mid = E.mean(1)
    uv, z = project_points(mid, T, CAM)
    col, row = np.floor(uv).astype(int).T
    ok = valid & inside & (col >= 0) & (col < CAM.width) & (row >= 0) & (row < CAM.height)
    vis = ok.copy()
    vis[ok] = np.abs(depth[row[ok], col[ok]] - z[ok]) < 0.05
    return E[vis], segs[vis].reshape(-1, 4)


POSES = [lookat([1.2, -1.0, 1.0], [0, 0, 4]), lookat([0.6, -1.3, 0.8], [0, 0, 4])]


def to_world(seg_cam, T):
    return (seg_cam - T[:3, 3]) @ T[:3, :3]


class TestLiftView:
    def test_edges_lifted_on_cube_never_on_wall(self):
        T = POSES[0]
        D = render_depth(T)
        E, segs = visible_edges_2d(T, D)
        assert len(E) >= 8  # of 9 visible (a silhouette midpoint may fall on a background pixel)
        out, ok = lift_view_lines(segs, D, CAM)
        assert ok.sum() >= 6
        err = np.array([point_line_distance(to_world(out[i], T), E[i]).max() for i in np.flatnonzero(ok)])
        # the 3x3 median at a convex crease reads a little deep: a short receding edge (26 px
        # spanning 2.6 -> 3.5 m) is off by 3 cm at its far end; most are within 1 cm
        assert err.max() < 0.06 and np.median(err) < 0.01, err
        # each lifted segment projects exactly onto its detection
        back, _ = project_segments(np.array([to_world(out[i], T) for i in np.flatnonzero(ok)]), T, CAM)
        np.testing.assert_allclose(back.reshape(-1, 4), segs[ok], atol=1e-6)

    def test_discontinuous_line_rejected(self):
        T = POSES[0]
        D = render_depth(T)
        uv, _ = project_points(np.array([[0.0, 0.0, 3.5], [2.5, 0.0, 5.95]]), T, CAM)  # cube face -> wall
        out, ok = lift_view_lines(uv.reshape(1, 4), D, CAM)
        assert not ok[0] and np.isnan(out[0]).all()

    def test_no_depth_no_lines(self):
        out, ok = lift_view_lines(np.array([[10.0, 10.0, 100.0, 50.0]]), np.zeros((240, 320), np.float32), CAM)
        assert not ok.any()
        out, ok = lift_view_lines(np.zeros((0, 4)), np.zeros((240, 320), np.float32), CAM)
        assert out.shape == (0, 2, 3)


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("lift")
    views = []
    (root / "wf").mkdir()
    for k, T in enumerate(POSES):
        D = render_depth(T)
        write_depth(root / f"d{k}.png", D)
        _, segs = visible_edges_2d(T, D)
        np.savez(root / "wf" / f"v{k}.npz", lines=segs)
        views.append(View(f"v{k}.png", CAM, T, root / f"c{k}.png", depth_path=root / f"d{k}.png"))
    lines_h5 = import_lines(views, root / "wf", root / "lines2d.h5")
    return root, views, lines_h5


class TestLiftMap:
    def test_lift_and_evaluate(self, scene_files):
        root, views, lines_h5 = scene_files
        lm = lift_linemap(views, lines_h5)
        assert len(lm) >= 10
        assert all(len(t) == 1 for t in lm.tracks) and (lm.supports == 1).all()
        assert {t[0].image_name for t in lm.tracks} == {"v0.png", "v1.png"}
        res = evaluate_linemap(lm, CUBE, m1_thresholds=(0.02, 0.06), gt_points_per_m2=2000)
        assert res["M1"]["line"]["prec@0.06"] == 1.0 and res["M1"]["line"]["prec@0.02"] > 0.95
        assert res["M1"]["line"]["acc"] < 0.01
        out = main(views, lines_h5, root / "linemap.h5")
        assert LineMap.load(out).metadata["method"] == "lift"

    def test_merge(self, scene_files):
        _, views, lines_h5 = scene_files
        single = lift_linemap(views, lines_h5)
        merged = lift_linemap(views, lines_h5, LiftConfig(merge=True, merge_max_angle=0.03, merge_max_dist=3.0))
        assert len(merged) < len(single)
        multi = [i for i, t in enumerate(merged.tracks) if len({o.image_name for o in t}) == 2]
        assert len(multi) >= 3
        E = cube_edges()
        for i in multi:
            d = min(point_line_distance(merged.lines[i], e).max() for e in E)
            assert d < 0.02
        assert merged.metadata["n_before_merge"] == len(single)


def test_lift_redkitchen(redkitchen_root, tmp_path):
    from lipmap.datasets import load_scene

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    views = scene.mapping[0:6:2]
    lines_h5 = detect_lines(views, tmp_path / "lines2d.h5")
    lm = lift_linemap(views, lines_h5)
    assert len(lm) > 300
    # GT from the interleaved frames: other depth frames than the ones lifted
    gt = gt_from_depth(scene.mapping[1:7:2], voxel=0.01, stride=2)
    res = evaluate_linemap(lm, gt, conf="fast")
    assert res["M1"]["line"]["prec@0.05"] > 0.9
    assert res["M2"]["P@50mm"] > 90
