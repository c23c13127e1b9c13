"""The reuse rule of cached artifacts (lipmap.artifacts): reuse only what the same settings made."""
import h5py
import numpy as np
import pytest

from lipmap.artifacts import (Stamp, StaleArtifactError, describe_difference, digest, read_stamp, reuse, scene_key,
                              variant_dir, views_key, write_stamp)
from lipmap.testing import wall_scene


def _h5(path, stamp=None):
    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=np.arange(3))
        if stamp is not None:
            for k, v in stamp.h5_attrs().items():
                f.attrs[k] = v
    return path


def test_digest_is_canonical():
    assert digest({"a": 1, "b": [1.0, 2]}) == digest({"b": [1.0, 2], "a": 1})
    assert digest({"a": 1}) != digest({"a": 2})
    assert Stamp("s", {"a": 1}).digest != Stamp("t", {"a": 1}).digest


def test_reuse_only_with_the_same_settings(tmp_path):
    a, b = Stamp("lines2d", {"detector": "lsd", "min_length": 15}), Stamp("lines2d", {"detector": "lsd", "min_length": 30})
    path = tmp_path / "lines2d.h5"
    assert reuse(path, a) is False  # nothing there
    _h5(path, a)
    assert read_stamp(path) == a and reuse(path, a) is True
    with pytest.raises(StaleArtifactError, match=r"lines2d\.h5: was made by lines2d with other settings .*min_length: 15 -> 30"):
        reuse(path, b)
    assert path.exists()  # a refusal touches nothing
    assert reuse(path, b, replace_stale=True) is False and not path.exists()  # cheap steps redo instead
    _h5(path, a)
    assert reuse(path, a, overwrite=True) is False and not path.exists()


def test_an_artifact_without_a_stamp_is_never_reused(tmp_path):
    path = _h5(tmp_path / "planes.h5")
    with pytest.raises(StaleArtifactError, match="no record of the settings"):
        reuse(path, Stamp("planes", {}))


def test_text_files_and_folders_carry_their_stamp(tmp_path):
    s = Stamp("pairs", {"k": 10})
    txt = tmp_path / "pairs.txt"
    txt.write_text("a b\n")
    write_stamp(txt, s)
    assert (tmp_path / "pairs.txt.stamp.json").exists() and reuse(txt, s)
    model = tmp_path / "sfm"
    model.mkdir()
    write_stamp(model, s)
    assert (model / "lipmap-stamp.json").exists() and reuse(model, s)
    assert reuse(model, Stamp("pairs", {"k": 5}), replace_stale=True) is False and not model.exists()


def test_describe_difference_names_the_shallowest_keys_first():
    old = Stamp("linemap", {"method": "lift", "lift": {"x": 1}, "scene": {"views": 1}})
    new = Stamp("linemap", {"method": "lipmap", "mapping": {"y": 2}, "scene": {"views": 2}})
    text = describe_difference(old, new)
    assert text.index("method: 'lift' -> 'lipmap'") < text.index("scene.views: 1 -> 2")
    assert "lift: {...} -> '<unset>'" in text


def test_input_keys_change_with_poses_and_pose_source(tmp_path):
    corners, views = wall_scene()
    k = views_key(views)
    moved = [v.with_pose(v.cam_from_world @ np.diag([1.0, 1.0, 1.0, 1.0])) for v in views]
    assert views_key(moved) == k
    moved[0] = views[0].with_pose(views[0].cam_from_world + np.eye(4) * 0)
    moved[0].cam_from_world[0, 3] += 1e-3
    assert views_key(moved) != k

    class S:
        name, dataset, depth_registered, meta, mapping = "s", "7scenes", True, {}, views
    a, b = S(), S()
    b.pose_source = "sfm"
    a.pose_source = "posetxt"
    assert scene_key(a) != scene_key(b)
    assert variant_dir(tmp_path, "map-lift-fast", Stamp("linemap", scene_key(a))).name.startswith("map-lift-fast-")


def test_source_digest_follows_the_code_it_covers_only(tmp_path):
    from lipmap.artifacts import source_digest

    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for rel, text in (("a.py", "A = 1\n"), ("sub/b.py", "B = 1\n"), ("viz.py", "V = 1\n")):
        (pkg / rel).write_text(text)
    only = ("a.py", "sub")
    d0, all0 = source_digest([pkg], only), source_digest([pkg])
    (pkg / "viz.py").write_text("V = 2\n")
    assert source_digest([pkg], only) == d0 and source_digest([pkg]) != all0
    (pkg / "sub" / "b.py").write_text("B = 2\n")
    assert source_digest([pkg], only) != d0


def test_source_digest_ignores_comments_blank_lines_and_docstrings(tmp_path):
    """Editing prose in the code keeps the artifacts (a full scene's planes take hours); editing code does not."""
    from lipmap.artifacts import source_digest

    pkg = tmp_path / "pkg"
    pkg.mkdir()
    f = pkg / "a.py"
    f.write_text('"""Module doc."""\n\n\ndef f(x):\n    """Doc."""\n    return x + 1  # why\n')
    d0 = source_digest([pkg])
    f.write_text('"""Another module doc,\nover two lines."""\n# a comment\n\ndef f(x):\n    """Other doc."""\n\n'
                 '    return x + 1  # another why\n')
    assert source_digest([pkg]) == d0
    for code in ('def f(x):\n    return x + 2\n',                        # a constant
                 'def f(x):\n    """Doc."""\n    return x + 1\nS = "data"\n',  # a string that is data
                 'def f(x):\n    "Doc."\n    return x - 1\n',              # an operator
                 'def f(x):\n    return (x\n            + 1)\nf(1)\n'):       # a statement
        f.write_text(code)
        assert source_digest([pkg]) != d0, code
    f.write_text("def f(x):\n    return x + 1\n")
    assert source_digest([pkg]) == d0
    f.write_text("def f(:\n")  # does not tokenize: taken byte for byte, still a digest
    assert len(source_digest([pkg])) == 12


def test_source_digest_entries_may_name_files_in_folders(tmp_path):
    from lipmap.artifacts import source_digest

    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for rel in ("sub/b.py", "sub/c.py", "subway.py"):
        (pkg / rel).write_text("X = 1\n")
    d0 = source_digest([pkg], ("sub/b.py",))
    (pkg / "sub" / "c.py").write_text("X = 2\n")
    (pkg / "subway.py").write_text("X = 2\n")
    assert source_digest([pkg], ("sub/b.py",)) == d0
    (pkg / "sub" / "b.py").write_text("X = 2\n")
    assert source_digest([pkg], ("sub/b.py",)) != d0


def _lipmap_imports(path, root):
    """The lipmap modules (files) that ``path`` imports anywhere in it, with the packages' ``__init__.py`` on the way."""
    import ast

    parts = path.relative_to(root.parent).with_suffix("").parts
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = parts[: len(parts) - node.level]
                mod = base + (tuple(node.module.split(".")) if node.module else ())
            elif node.module and node.module.split(".")[0] == "lipmap":
                mod = tuple(node.module.split("."))
            else:
                continue
            names = [mod] + [mod + (a.name,) for a in node.names]
        elif isinstance(node, ast.Import):
            names = [tuple(a.name.split(".")) for a in node.names if a.name.split(".")[0] == "lipmap"]
        else:
            continue
        for m in names:
            for k in range(1, len(m) + 1):
                for f in (root.parent.joinpath(*m[:k]).with_suffix(".py"), root.parent.joinpath(*m[:k], "__init__.py")):
                    if f.exists():
                        found.add(f)
    return found


def test_the_planes_code_holds_everything_the_plane_step_imports():
    """planes.h5 is stamped with the digest of PLANES_CODE only: a lipmap module the plane step imports (at any depth,
    in any function) but PLANES_CODE leaves out would let planes made by other code be reused."""
    from pathlib import Path

    import lipmap
    from lipmap.artifacts import MAPPING_CODE, PLANES_CODE, _covered

    root = Path(lipmap.__file__).parent
    assert all((root / name).exists() for name in PLANES_CODE)
    todo = [root / "planes" / "train.py", root / "mapping" / "joint.py"]
    seen = set()
    while todo:
        f = todo.pop()
        if f not in seen:
            seen.add(f)
            todo.extend(_lipmap_imports(f, root))
    assert root / "mapping" / "supervision.py" in seen and root / "geometry.py" in seen  # the walk follows imports
    plumbing = {"__init__.py", "errors.py", "artifacts.py", "mapping/__init__.py"}  # no effect on the numbers
    missing = [f.relative_to(root).as_posix() for f in seen
               if f.relative_to(root).as_posix() not in plumbing and not _covered(f.relative_to(root), PLANES_CODE)]
    assert not missing, f"the plane step imports {missing}, which PLANES_CODE leaves out"
    # and what makes the planes also makes the map
    assert all(_covered(Path(e), MAPPING_CODE) for e in PLANES_CODE)


def test_the_mapping_code_names_modules_that_exist():
    from pathlib import Path

    import lipmap
    from lipmap.artifacts import MAPPING_CODE

    root = Path(lipmap.__file__).parent
    assert all((root / name).exists() for name in MAPPING_CODE)
    # what makes a map is covered: every module the mapping pipeline imports from lipmap
    assert {"mapping", "planes", "lines2d.py", "lift.py", "geometry.py"} <= set(MAPPING_CODE)
