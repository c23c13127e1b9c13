"""Planes container: conventions (vertex/edge order, axes), re-centring, sanitizing, HDF5/PLY I/O."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lipmap.errors import InputError
from lipmap.planes import Planes, export_planes_ply, load_planes, save_planes
from lipmap.planes.primitives import R_MAX, R_MIN, quat_to_rotmat, rotation_from_normals, rotmat_to_quat, triangle_mesh
from lipmap.poses import qvec_wxyz_to_R


def one_plane(radii=(0.4, 0.1, 0.3, 0.2)):
    # identity rotation: X = world x, Y = world y, normal = world z
    return Planes(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([radii]))


class TestConventions:
    def test_corners_paper_order(self):
        """Convention pin: v1 = c + x+ X + y+ Y, v2 = c + x+ X - y- Y, v3 = c - x- X - y- Y, v4 = c - x- X + y+ Y."""
        v = one_plane().corners()[0]
        c = torch.tensor([1.0, 2.0, 3.0])
        expected = torch.stack([c + torch.tensor([0.4, 0.3, 0]), c + torch.tensor([0.4, -0.2, 0]),
                                c + torch.tensor([-0.1, -0.2, 0]), c + torch.tensor([-0.1, 0.3, 0])])
        torch.testing.assert_close(v, expected)

    def test_edges(self):
        p = one_plane()
        v, e = p.corners()[0], p.edges()[0]
        assert e.shape == (4, 2, 3)
        for i, (a, b) in enumerate([(0, 1), (1, 2), (2, 3), (3, 0)]):
            torch.testing.assert_close(e[i, 0], v[a])
            torch.testing.assert_close(e[i, 1], v[b])

    def test_axes_from_quaternion(self):
        q = np.array([0.8, 0.2, -0.3, 0.4])
        q /= np.linalg.norm(q)
        p = Planes(torch.zeros(1, 3, dtype=torch.float64), torch.tensor(q[None] * 3.0), torch.full((1, 4), 0.1, dtype=torch.float64))
        R = qvec_wxyz_to_R(q)  # the numpy twin in lipmap.poses
        torch.testing.assert_close(p.rotation()[0], torch.tensor(R))
        torch.testing.assert_close(p.normal[0], torch.tensor(R[:, 2]))
        torch.testing.assert_close(p.x_axis[0], torch.tensor(R[:, 0]))

    def test_radii_clamped_in_use(self):
        p = one_plane((1.0, -1.0, 0.2, 0.0))
        torch.testing.assert_close(p.radii_clamped()[0], torch.tensor([R_MAX, R_MIN, 0.2, R_MIN]))

    def test_rotation_from_normals_deterministic(self):
        n = np.random.default_rng(0).normal(size=(50, 3))
        R = rotation_from_normals(n)
        assert np.allclose(R[:, :, 2], n / np.linalg.norm(n, axis=1, keepdims=True))
        assert np.allclose(np.einsum("kij,kil->kjl", R, R), np.eye(3), atol=1e-12)
        assert np.allclose(np.linalg.det(R), 1)
        assert np.array_equal(R, rotation_from_normals(n))
        q = rotmat_to_quat(R)
        torch.testing.assert_close(quat_to_rotmat(torch.tensor(q)), torch.tensor(R))


class TestRecenter:
    def test_same_rectangle(self):
        p = one_plane()
        r = p.recentered()
        torch.testing.assert_close(r.radii[0], torch.tensor([0.25, 0.25, 0.25, 0.25]))
        # centre moves by (x+ - x-)/2 along X and (y+ - y-)/2 along Y
        torch.testing.assert_close(r.center[0], torch.tensor([1.15, 2.05, 3.0]))
        # the same four vertices (as a set)
        a = p.corners()[0].numpy()
        b = r.corners()[0].numpy()
        assert np.allclose(np.sort(a, axis=0), np.sort(b, axis=0), atol=1e-6)


class TestSanitize:
    def test_degenerate_removed(self):
        c = torch.zeros(5, 3)
        q = torch.tensor([[1.0, 0, 0, 0]] * 5)
        r = torch.full((5, 4), 0.1)
        c[1, 0] = float("nan")
        q[2] = 0
        r[3, 2] = 0.0
        r[4, 0] = -0.2
        s, keep = Planes(c, q, r).sanitized()
        assert keep.tolist() == [True, False, False, False, False]
        assert len(s) == 1

    def test_shape_errors(self):
        with pytest.raises(InputError):
            Planes(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2, 4))
        with pytest.raises(InputError):
            Planes(torch.zeros(2, 3), torch.zeros(3, 4), torch.zeros(2, 4))


class TestIO:
    def test_h5_roundtrip(self, tmp_path):
        p = Planes.from_normals(np.random.rand(7, 3), np.random.rand(7, 3) - 0.5, np.full(7, 0.05))
        path = save_planes(tmp_path / "planes.h5", p, attrs={"hello": [1, 2]})
        q = load_planes(path)
        for a, b in zip(p.tensors(), q.tensors()):
            torch.testing.assert_close(a, b)
        from lipmap.planes.io import load_planes_meta

        assert load_planes_meta(path) == {"hello": [1, 2]}
        assert not list(tmp_path.glob("*.tmp*"))

    def test_load_errors(self, tmp_path):
        with pytest.raises(InputError, match="missing"):
            load_planes(tmp_path / "nope.h5")
        bad = tmp_path / "bad.h5"
        bad.write_text("not hdf5")
        with pytest.raises(InputError, match="bad.h5"):
            load_planes(bad)
        import h5py

        with h5py.File(tmp_path / "other.h5", "w") as f:
            f["center"] = np.zeros((2, 3))
        with pytest.raises(InputError, match="not a planes file"):
            load_planes(tmp_path / "other.h5")

    def test_ply_mesh(self, tmp_path):
        import trimesh

        p = one_plane()
        path = export_planes_ply(tmp_path / "planes.ply", Planes.cat([p, p.recentered()]))
        m = trimesh.load(path, process=False)
        assert len(m.faces) == 4 and len(m.vertices) == 8
        assert m.area == pytest.approx(2 * 0.5 * 0.5)
        # face normals agree with the plane normal (+z here)
        assert np.allclose(m.face_normals, [0, 0, 1])

    def test_triangle_winding(self):
        V, F = triangle_mesh(Planes.from_normals([[0, 0, 0]], [[0.3, -0.2, 0.9]], [0.1]))
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        assert np.allclose(n, np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9]), atol=1e-6)
