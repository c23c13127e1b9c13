"""Tests for the procedural synthetic scene generator (lipmap.datasets.synthetic).

The small scene room-s3 is generated once per session by the ``synthetic_root`` fixture (conftest.py);
the determinism tests use a tiny configuration so they can generate several scenes in seconds.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from lipmap.errors import InputError
from lipmap.imageio import read_color, read_depth, read_normals
from lipmap.poses import invert_T, rotation_error_deg
from lipmap.scene import Camera
from lipmap.geometry import backproject_depth as backproject, project_cam_points as project
from lipmap.datasets.synthetic import (
    SYNTH_PRESETS,
    SynthConfig,
    add_synth_parser,
    cli_synth,
    corrupt_depth,
    generate_scene,
    look_rotation,
)

SCENE = "room-s3"
TINY = SynthConfig("tiny", 96, 72, 78.75, 78.75, 48.0, 36.0, n_mapping=4, n_query=3, texels_per_m=64.0)


@pytest.fixture(scope="module")
def scene_dir(synthetic_root) -> Path:
    return synthetic_root / SCENE


@pytest.fixture(scope="module")
def meta(scene_dir) -> dict:
    return json.loads((scene_dir / "scene.json").read_text())


@pytest.fixture(scope="module")
def camera(meta) -> Camera:
    return Camera(meta["width"], meta["height"], tuple(meta["intrinsics"]))


def _frames(scene_dir: Path, seq: str) -> list[Path]:
    return sorted((scene_dir / seq).glob("frame-*.pose.txt"))


def _cam_from_world(pose_path: Path) -> np.ndarray:
    return invert_T(np.loadtxt(pose_path))


def _stem(pose_path: Path) -> str:
    return str(pose_path)[: -len(".pose.txt")]


class TestLayout:
    def test_files(self, scene_dir, meta):
        assert (scene_dir / "TrainSplit.txt").read_text().split() == ["sequence1"]
        assert (scene_dir / "TestSplit.txt").read_text().split() == ["sequence2"]
        for seq, n in (("seq-01", meta["n_mapping"]), ("seq-02", meta["n_query"])):
            poses = _frames(scene_dir, seq)
            assert [p.name for p in poses] == [f"frame-{i:06d}.pose.txt" for i in range(n)]
            for p in poses:
                for ext in ("color.png", "depth.png", "normal.png"):
                    assert Path(f"{_stem(p)}.{ext}").is_file()
        assert (scene_dir / "mesh.ply").is_file() and (scene_dir / "surfaces.json").is_file()
        assert not list(scene_dir.rglob("*.tmp*")), "atomic writes left temporary files"

    def test_scene_json(self, meta):
        small = SYNTH_PRESETS["small"]
        assert meta["dataset"] == "synthetic" and meta["generator_version"] == 1
        assert (meta["width"], meta["height"]) == (320, 240)
        assert meta["intrinsics"] == [262.5, 262.5, 160.0, 120.0]
        assert meta["depth_registered"] is True
        assert meta["seed"] == 3 and meta["preset"] == "small"
        assert (meta["n_mapping"], meta["n_query"]) == (small.n_mapping, small.n_query) == (30, 20)
        assert 0.05 < meta["plain_surface_fraction"] < 0.6
        Lx, Ly, H = meta["room_size"]
        assert 4.0 <= Lx <= 6.0 and 3.0 <= Ly <= 5.0 and 2.6 <= H <= 3.0

    def test_image_formats(self, scene_dir, camera):
        stem = _stem(_frames(scene_dir, "seq-01")[0])
        rgb = cv2.imread(f"{stem}.color.png", cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
        raw = cv2.imread(f"{stem}.depth.png", cv2.IMREAD_UNCHANGED)
        assert raw.shape == (240, 320) and raw.dtype == np.uint16
        assert (raw > 0).all(), "a closed room: every pixel sees a surface"
        T = np.loadtxt(f"{stem}.pose.txt")
        assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)

    def test_skip_existing(self, synthetic_root, scene_dir):
        before = (scene_dir / "scene.json").stat().st_mtime_ns
        assert generate_scene(synthetic_root, seed=3, preset="small") == scene_dir
        assert (scene_dir / "scene.json").stat().st_mtime_ns == before
        with pytest.raises(InputError, match="preset"):
            generate_scene(synthetic_root, seed=3, preset="default")
        with pytest.raises(InputError, match="unknown synthetic preset"):
            generate_scene(synthetic_root, seed=3, preset="huge")
        with pytest.raises(InputError, match="non-negative"):
            generate_scene(synthetic_root, seed=-1)


class TestDeterminism:
    @staticmethod
    def _all_files(d: Path) -> dict:
        return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}

    def test_same_seed_same_bytes(self, tmp_path):
        a = generate_scene(tmp_path / "a", seed=3, preset=TINY)
        b = generate_scene(tmp_path / "b", seed=3, preset=TINY)
        fa, fb = self._all_files(a), self._all_files(b)
        assert len(fa) == 4 + 4 * 7 + 1  # splits, mesh, surfaces, scene.json; 4 files x 7 frames; + nothing else
        assert fa == fb
        # overwrite regenerates the same bytes
        generate_scene(tmp_path / "a", seed=3, preset=TINY, overwrite=True)
        assert self._all_files(a) == fb

    def test_different_seed_different_room(self, tmp_path):
        a = generate_scene(tmp_path, seed=3, preset=TINY)
        b = generate_scene(tmp_path, seed=4, preset=TINY)
        assert b.name == "room-s4"
        assert (a / "mesh.ply").read_bytes() != (b / "mesh.ply").read_bytes()
        assert json.loads((a / "scene.json").read_text())["room_size"] != json.loads(
            (b / "scene.json").read_text())["room_size"]
        ia = read_color(a / "seq-01/frame-000000.color.png").astype(int)
        ib = read_color(b / "seq-01/frame-000000.color.png").astype(int)
        assert np.abs(ia - ib).mean() > 10

    def test_incomplete_scene_is_redone(self, tmp_path):
        d = generate_scene(tmp_path, seed=3, preset=TINY)
        ref = self._all_files(d)
        (d / "scene.json").unlink()  # as if the run was killed before the end
        stale = d / "seq-01" / "frame-000099.color.png"
        stale.write_bytes(b"stale")
        generate_scene(tmp_path, seed=3, preset=TINY)
        assert not stale.exists()
        assert self._all_files(d) == ref

    def test_room_does_not_depend_on_preset(self, scene_dir, tmp_path):
        """The room has its own random stream: the tiny preset builds room-s3's mesh bit for bit."""
        tiny = generate_scene(tmp_path, seed=3, preset=TINY)
        assert (tiny / "mesh.ply").read_bytes() == (scene_dir / "mesh.ply").read_bytes()
        assert (tiny / "surfaces.json").read_bytes() == (scene_dir / "surfaces.json").read_bytes()


class TestNoisyDepth:
    def test_corrupt_depth_statistics(self):
        z = np.full((240, 320), 3.0)
        z[:10] = 0.0  # no surface stays no surface
        a = corrupt_depth(z, np.random.default_rng(0), 0.02)
        np.testing.assert_array_equal(a, corrupt_depth(z, np.random.default_rng(0), 0.02))  # seeded
        assert (a[:10] == 0).all() and (a[10:] > 0).all()
        rel = a[10:] / 3.0 - 1.0
        # smooth warp: neighbours differ by the per-pixel noise only (Kinect sigma at 3 m: 14 mm)
        step = np.diff(a[10:], axis=1).std() / np.sqrt(2)
        assert 0.010 < step < 0.018
        assert 0.005 < np.abs(rel).mean() < 0.05  # the 2 % warp dominates
        no_warp = corrupt_depth(z, np.random.default_rng(0), 0.0)[10:]
        assert abs(no_warp.mean() - 3.0) < 1e-3 and 0.012 < no_warp.std() < 0.016  # per-pixel noise only

    def test_preset_corrupts_only_the_depth_files(self, tmp_path):
        from dataclasses import replace

        clean = generate_scene(tmp_path / "c", seed=3, preset=TINY)
        noisy = generate_scene(tmp_path / "n", seed=3, preset=replace(TINY, depth_warp_sigma=0.02))
        assert json.loads((noisy / "scene.json").read_text())["depth_warp_sigma"] == 0.02
        for kind in ("color", "normal", "pose"):
            f = f"seq-01/frame-000001.{kind}.{'txt' if kind == 'pose' else 'png'}"
            assert (clean / f).read_bytes() == (noisy / f).read_bytes()
        dc = read_depth(clean / "seq-01/frame-000001.depth.png")
        dn = read_depth(noisy / "seq-01/frame-000001.depth.png")
        m = dc > 0
        assert ((dn > 0) == m).all()
        err = np.abs(dn - dc)[m]
        assert np.median(err) > 5e-3 and np.median(err / dc[m]) < 0.06
        assert SYNTH_PRESETS["small-noisy-depth"].depth_warp_sigma == 0.02


class TestGeometry:
    def test_depth_matches_mesh(self, scene_dir, camera):
        mesh = trimesh.load(scene_dir / "mesh.ply", process=False)
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        ray = RayMeshIntersector(mesh)
        rng = np.random.default_rng(0)
        rays = camera.pixel_rays()
        errs = []
        for pose in _frames(scene_dir, "seq-01")[::7] + _frames(scene_dir, "seq-02")[::9]:
            T = _cam_from_world(pose)
            depth = read_depth(Path(f"{_stem(pose)}.depth.png"))
            r, c = rng.integers(0, camera.height, 300), rng.integers(0, camera.width, 300)
            d_cam = rays[r, c]  # through pixel centres (c + 0.5, r + 0.5)
            center = -T[:3, :3].T @ T[:3, 3]
            d_world = d_cam @ T[:3, :3]
            loc, idx, tri = ray.intersects_location(np.tile(center, (len(r), 1)), d_world, multiple_hits=False)
            assert len(idx) == len(r)
            # every surface is seen from its front: mesh normals (winding) point into the room
            assert (np.einsum("ij,ij->i", mesh.face_normals[tri], d_world[idx]) < 0).all()
            z = (loc @ T[:3, :3].T + T[:3, 3])[:, 2]
            errs.append(np.abs(z - depth[r[idx], c[idx]]))
        errs = np.concatenate(errs)
        # PNG millimetres round by <= 0.5 mm; a half-pixel shift would cost cm on slanted floors
        assert np.percentile(errs, 99) < 1e-3 and np.median(errs) < 6e-4

    def test_multiview_depth_consistency(self, scene_dir, camera):
        frames = _frames(scene_dir, "seq-01")
        meds = []
        for i, j in ((0, 1), (5, 6), (10, 12), (20, 21)):
            Ti, Tj = _cam_from_world(frames[i]), _cam_from_world(frames[j])
            di = read_depth(Path(f"{_stem(frames[i])}.depth.png"))
            dj = read_depth(Path(f"{_stem(frames[j])}.depth.png"))
            pts, _ = backproject(di, camera)
            j_from_i = Tj @ invert_T(Ti)
            pj = pts @ j_from_i[:3, :3].T + j_from_i[:3, 3]
            uv, z = project(pj, camera)
            col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (z > 0.1) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
            diff = z[inside] - dj[row[inside], col[inside]]
            visible = diff < 0.05  # farther than what frame j sees there: occluded
            assert visible.mean() > 0.3, f"frames {i} and {j} barely overlap"
            meds.append(np.median(np.abs(diff[visible])))
        assert max(meds) < 5e-3, meds

    def test_normals_unit_and_facing(self, scene_dir, camera):
        rays = camera.pixel_rays()
        for pose in _frames(scene_dir, "seq-01")[::6]:
            n = read_normals(Path(f"{_stem(pose)}.normal.png"))
            depth = read_depth(Path(f"{_stem(pose)}.depth.png"))
            norm = np.linalg.norm(n, axis=-1)
            assert np.allclose(norm[depth > 0], 1.0, atol=1e-3)
            assert (np.einsum("hwc,hwc->hw", n, rays)[depth > 0] < 0).all(), "normals must face the camera"
            # the normal of the plane through neighbouring back-projected points agrees
            P = rays * depth[..., None]
            g = np.cross(P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1])
            g /= np.linalg.norm(g, axis=-1, keepdims=True) + 1e-12
            cos = np.abs(np.einsum("hwc,hwc->hw", g, n[1:-1, 1:-1]))
            assert np.median(cos) > np.cos(np.radians(3))

    def test_cameras_inside_and_clear(self, scene_dir, meta):
        Lx, Ly, H = meta["room_size"]
        for seq in ("seq-01", "seq-02"):
            for pose in _frames(scene_dir, seq):
                c = np.loadtxt(pose)[:3, 3]
                assert 0.3 < c[0] < Lx - 0.3 and 0.3 < c[1] < Ly - 0.3 and 1.2 <= c[2] <= 1.7
                depth = read_depth(Path(f"{_stem(pose)}.depth.png"))
                assert depth[depth > 0].min() >= 0.499, f"{pose.name}: a surface closer than 0.5 m"

    def test_look_rotation_convention(self):
        """Convention pin: the camera looks along +z, x right, y down, in a z-up world."""
        R_wc = look_rotation(0.0, 0.0, 0.0)
        assert np.allclose(R_wc[:, 2], [1, 0, 0])  # forward = heading 0 = +x
        assert np.allclose(R_wc[:, 0], [0, -1, 0])  # right of +x (seen from above, z up) is -y
        assert np.allclose(R_wc[:, 1], [0, 0, -1])  # image down = world down
        assert np.isclose(np.linalg.det(R_wc), 1.0)
        R = look_rotation(0.3, -0.2, 0.0)
        assert R[2, 2] < 0  # pitched down: forward has a negative z component


class TestAppearance:
    @staticmethod
    def _local_gradient(gray: np.ndarray) -> np.ndarray:
        g = gray.astype(np.float32)
        gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
        return np.sqrt(cv2.blur(gx * gx + gy * gy, (9, 9)))

    def test_textured_and_plain_regions(self, scene_dir, meta):
        textured, plain = [], []
        for pose in _frames(scene_dir, "seq-01"):
            e = self._local_gradient(read_color(Path(f"{_stem(pose)}.color.png"), gray=True))
            textured.append((e > 25).mean())
            plain.append((e < 10).mean())  # pixel noise alone gives ~5
        assert np.mean(textured) > 0.5
        assert 0.03 < np.mean(plain) < 0.45
        assert 0.05 < meta["plain_pixel_fraction"] < 0.6

    def test_sift_keypoints(self, scene_dir):
        sift = cv2.SIFT_create()
        counts = [len(sift.detect(read_color(Path(f"{_stem(p)}.color.png"), gray=True)))
                  for p in _frames(scene_dir, "seq-01")]
        assert np.mean(np.array(counts) > 300) >= 0.7, counts

    def test_queries_near_mapping(self, scene_dir):
        M = np.array([np.loadtxt(p) for p in _frames(scene_dir, "seq-01")])
        Q = np.array([np.loadtxt(p) for p in _frames(scene_dir, "seq-02")])
        d = np.linalg.norm(Q[:, None, :3, 3] - M[None, :, :3, 3], axis=-1)
        nearest = d.argmin(1)
        assert np.median(d.min(1)) < 0.4 and d.min() > 0.03  # near, but a different pass
        rot = [rotation_error_deg(Q[i, :3, :3], M[k, :3, :3]) for i, k in enumerate(nearest)]
        assert 2.0 < np.median(rot) < 15.0


    def test_queries_localize_with_points(self, scene_dir, camera):
        """The passes overlap enough for point localization: SIFT matches to the 3 nearest mapping
        frames, lifted to 3D with their depth and pose, give PnP poses within 5 cm / 5 deg."""
        sift, bf, K = cv2.SIFT_create(), cv2.BFMatcher(), camera.K

        def frame(pose):
            kp, de = sift.detectAndCompute(read_color(Path(f"{_stem(pose)}.color.png"), gray=True), None)
            # cv2 keypoints have pixel centres at integers; +0.5 -> COLMAP convention
            return _cam_from_world(pose), np.array([k.pt for k in kp]) + 0.5, de, Path(f"{_stem(pose)}.depth.png")

        mapping = [frame(p) for p in _frames(scene_dir, "seq-01")]
        centers = np.array([-T[:3, :3].T @ T[:3, 3] for T, *_ in mapping])
        ok = []
        for pose in _frames(scene_dir, "seq-02")[::2]:
            Tq, kq, dq, _ = frame(pose)
            near = np.argsort(np.linalg.norm(centers - (-Tq[:3, :3].T @ Tq[:3, 3]), axis=1))[:3]
            p3, p2 = [], []
            for k in near:
                Tm, km, dm, depth_path = mapping[k]
                depth = read_depth(depth_path)
                for a, b in bf.knnMatch(dq, dm, k=2):
                    if a.distance < 0.8 * b.distance:
                        u, v = km[a.trainIdx]
                        z = depth[int(v), int(u)]
                        x_cam = np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0]) * z
                        p3.append(Tm[:3, :3].T @ (x_cam - Tm[:3, 3]))
                        p2.append(kq[a.queryIdx] - 0.5)  # back to OpenCV's pixel centres for solvePnP
            found, rvec, tvec, _ = cv2.solvePnPRansac(np.array(p3), np.array(p2), K, None, reprojectionError=3.0,
                                                      iterationsCount=1000)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
            dt = np.linalg.norm((-T[:3, :3].T @ T[:3, 3]) - (-Tq[:3, :3].T @ Tq[:3, 3]))
            ok.append(found and dt < 0.05 and rotation_error_deg(Tq[:3, :3], T[:3, :3]) < 5)
        assert np.mean(ok) >= 0.9, ok


class TestReaderAndCli:
    def test_load_scene(self, synthetic_root, scene_dir, camera):
        from lipmap.datasets import load_scene

        scene = load_scene("synthetic", synthetic_root, SCENE)
        assert len(scene.mapping) == 30 and len(scene.query) == 20
        assert scene.dataset == "synthetic" and scene.gt_mesh == scene_dir / "mesh.ply"
        v = scene.query[3]
        assert v.name == "seq-02/frame-000003.color.png"
        assert v.camera == camera and v.depth_camera is None
        assert np.allclose(v.cam_from_world, np.linalg.inv(np.loadtxt(scene_dir / "seq-02/frame-000003.pose.txt")),
                           atol=1e-9)
        assert np.array_equal(v.load_depth(), read_depth(scene_dir / "seq-02/frame-000003.depth.png"))
        assert v.load_normals().shape == (240, 320, 3)
        assert v.load_color().shape == (240, 320, 3)

    def test_cli(self, synthetic_root, scene_dir, capsys):
        parser = argparse.ArgumentParser()
        add_synth_parser(parser.add_subparsers(dest="cmd"))
        args = parser.parse_args(["synth", "--out", str(synthetic_root), "--seed", "3"])
        assert (args.seed, args.preset, args.overwrite, args.workers) == (3, "small", False, 1)
        big = parser.parse_args(["synth", "--out", "x", "--preset", "large", "--workers", "2"])
        assert (big.preset, big.workers) == ("large", 2)
        assert args.func(args) == scene_dir  # exists: skipped, path printed
        assert capsys.readouterr().out.strip() == str(scene_dir)
        assert args.func is cli_synth
        with pytest.raises(SystemExit):
            parser.parse_args(["synth", "--out", "x", "--preset", "huge"])


# tiny multi-room scene: the "medium" preset (2 rooms) at thumbnail size, 4+3 and 4+2 frames per room
MULTI = {"preset": "medium", "width": 80, "height": 60, "fx": 65.625, "fy": 65.625, "cx": 40.0, "cy": 30.0,
         "n_mapping": 8, "n_query": 5, "texels_per_m": 64.0}


@pytest.fixture(scope="module")
def multi_dir(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("multi"), seed=5, preset=MULTI)


class TestMultiRoom:
    def test_presets(self):
        large, medium = SYNTH_PRESETS["large"], SYNTH_PRESETS["medium"]
        assert (large.n_rooms, large.n_mapping, large.n_query, large.width, large.height) == (5, 1500, 500, 640, 480)
        assert (large.fx, large.fy, large.cx, large.cy) == (525.0, 525.0, 320.0, 240.0)
        assert medium.n_rooms == 2 and (medium.width, medium.height) == (640, 480)
        assert all(SYNTH_PRESETS[k].n_rooms == 1 for k in ("small", "default", "small-noisy-depth"))
        with pytest.raises(InputError, match="at least one mapping and one query frame"):
            generate_scene(Path("unused"), preset={**MULTI, "n_query": 1})

    def test_layout_and_splits(self, multi_dir):
        meta = json.loads((multi_dir / "scene.json").read_text())
        assert meta["n_rooms"] == 2 and meta["preset"] == "medium"
        assert (multi_dir / "TrainSplit.txt").read_text().split() == ["sequence1", "sequence3"]
        assert (multi_dir / "TestSplit.txt").read_text().split() == ["sequence2", "sequence4"]
        counts = {seq: len(_frames(multi_dir, seq)) for seq in ("seq-01", "seq-02", "seq-03", "seq-04")}
        assert counts == {"seq-01": 4, "seq-02": 3, "seq-03": 4, "seq-04": 2}
        r0, r1 = meta["rooms"]
        assert r0["offset"] == [0.0, 0.0, 0.0]
        assert r1["offset"][0] == pytest.approx(r0["size"][0] + meta["room_gap"]) and meta["room_gap"] > 0
        assert meta["room_size"][0] == pytest.approx(r1["offset"][0] + r1["size"][0])
        assert r1["surfaces"] == [r0["surfaces"][1], meta["n_surfaces"]]
        rows = json.loads((multi_dir / "surfaces.json").read_text())["surfaces"]
        assert [r["room"] for r in rows] == [0] * r0["surfaces"][1] + [1] * (meta["n_surfaces"] - r0["surfaces"][1])

    def test_cameras_in_own_room_and_depth_matches_mesh(self, multi_dir):
        meta = json.loads((multi_dir / "scene.json").read_text())
        camera = Camera(meta["width"], meta["height"], tuple(meta["intrinsics"]))
        mesh = trimesh.load(multi_dir / "mesh.ply", process=False)
        assert np.allclose(mesh.bounds, [[0, 0, 0], meta["room_size"]], atol=1e-6)  # the mesh covers all rooms
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        ray = RayMeshIntersector(mesh)
        rays = camera.pixel_rays().reshape(-1, 3)
        for r in meta["rooms"]:
            lo = np.array(r["offset"])
            hi = lo + r["size"]
            for seq in (r["mapping_sequence"], r["query_sequence"]):
                for pose in _frames(multi_dir, f"seq-{seq:02d}"):
                    c = np.loadtxt(pose)[:3, 3]
                    assert np.all(c > lo + 0.3) and np.all(c < hi - 0.3), f"{pose} is outside room {r['index']}"
                    T = _cam_from_world(pose)
                    depth = read_depth(Path(f"{_stem(pose)}.depth.png")).reshape(-1)
                    assert (depth >= 0.499).all()
                    d_world = rays @ T[:3, :3]
                    loc, idx, _ = ray.intersects_location(np.tile(c, (len(rays), 1)), d_world, multiple_hits=False)
                    assert len(idx) == len(rays)
                    assert np.all(loc >= lo - 1e-6) and np.all(loc <= hi + 1e-6)  # never sees another room
                    z = (loc @ T[:3, :3].T + T[:3, 3])[:, 2]
                    err = np.abs(z - depth[idx])
                    assert np.percentile(err, 99) < 1e-3, (pose, np.percentile(err, 99))

    def test_load_scene(self, multi_dir):
        from lipmap.datasets import load_scene

        scene = load_scene("synthetic", multi_dir.parent, multi_dir.name)
        assert [v.name for v in scene.mapping] == [f"seq-{s:02d}/frame-{i:06d}.color.png"
                                                   for s in (1, 3) for i in range(4)]
        assert [v.name for v in scene.query][-2:] == ["seq-04/frame-000000.color.png", "seq-04/frame-000001.color.png"]
        assert len(scene.query) == 5 and scene.gt_mesh == multi_dir / "mesh.ply"
        v = scene.mapping[5]
        assert np.allclose(v.cam_from_world, np.linalg.inv(np.loadtxt(multi_dir / "seq-03/frame-000001.pose.txt")),
                           atol=1e-9)

    def test_rooms_do_not_depend_on_room_count(self, multi_dir, tmp_path):
        """Room k has its own random streams: a 3-room scene starts with the 2-room scene's rooms, and the
        frames of room 0 do not change."""
        three = generate_scene(tmp_path, seed=5, preset={**MULTI, "n_rooms": 3, "n_mapping": 12, "n_query": 7})
        rows2 = json.loads((multi_dir / "surfaces.json").read_text())["surfaces"]
        rows3 = json.loads((three / "surfaces.json").read_text())["surfaces"]
        assert rows3[: len(rows2)] == rows2 and len(rows3) > len(rows2)
        for f in ("seq-01/frame-000002.color.png", "seq-03/frame-000003.pose.txt", "seq-04/frame-000001.depth.png"):
            assert (three / f).read_bytes() == (multi_dir / f).read_bytes()

    def test_workers_same_files(self, multi_dir, tmp_path):
        par = generate_scene(tmp_path, seed=5, preset=MULTI, workers=2)
        assert TestDeterminism._all_files(par) == TestDeterminism._all_files(multi_dir)
