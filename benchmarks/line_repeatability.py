"""How often a 2D line detector finds a line again in the next mapping view, by the paper's track test.

    python benchmarks/line_repeatability.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out MAP_DIR [--detectors lsd,lsd-dense,edlines,fld,LINES.h5] [--gaps 1,2,3] [--label TEXT]

The supports of a map (M2) count the mapping views whose detections pass the track builder's test (0.01 rad, 2 px,
overlap 0.2) against a line; they can be no higher than the detector's repeatability at that test. This measures
it without a line map in between: each detection of a mapping view (``MAP_DIR``'s planes, a ``lipmap-loc map
--method lipmap`` output, give its 3D place: five samples along it must hit planes and lie on one 3D line within
1 cm, so detections across occluding edges are left out) is projected into the view ``gap`` places further in the
mapping sequence; where it is visible there (the track builder's own test, past the planes) and at least 15 px long,
the detection of that view that overlaps it by more than 0.2 and is nearest in max(angle / 0.01, distance / 2) is
looked up. The table gives the share of such pairs with a detection within each angle / distance gate, for the next
view and, at the paper's gate, for views 2 and 3 places on and by the source detection's length. The planes and the
poses carry errors of their own, so the figures are a lower bound for the detector alone; they compare detectors
on equal terms. ``edlines`` and ``fld`` (OpenCV's EdgeDrawing and FastLineDetector) need
``pip install opencv-contrib-python-headless`` (the same OpenCV with the contrib modules); a name ending in ``.h5``
is a file of lines made elsewhere (a learned detector's, in the ``lines2d.h5`` format ``lipmap-loc map --lines``
writes); the others are :mod:`lipmap.lines2d` presets. Writes ``benchmarks/results/line-repeatability-<scene>.json`` and ``.png``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402
from single_view_lines import GATES, nearest_in_view  # noqa: E402

LENGTH_BINS = ((15, 30), (30, 60), (60, np.inf))


def contrib_detector(name: str):
    """OpenCV contrib's EdgeDrawing (``edlines``) or FastLineDetector (``fld``) with its defaults, as
    ``image -> (N, 4)`` lines in the COLMAP pixel convention."""
    import cv2

    if not hasattr(cv2, "ximgproc"):
        raise SystemExit(f"detector {name!r} needs OpenCV's contrib modules: pip install "
                         f"opencv-contrib-python-headless=={cv2.__version__} (cv2 {cv2.__version__} has no ximgproc)")

    def detect(image):
        if name == "edlines":
            ed = cv2.ximgproc.createEdgeDrawing()
            ed.detectEdges(image)
            raw = ed.detectLines()
        else:
            raw = cv2.ximgproc.createFastLineDetector().detect(image)
        return np.zeros((0, 4)) if raw is None else raw.reshape(-1, 4).astype(np.float64) + 0.5

    return detect


def detector(name: str):
    """``(view, image) -> (N, 4)`` for a :mod:`lipmap.lines2d` preset, an OpenCV contrib detector, or an HDF5 file of
    lines made elsewhere (``lines2d.h5`` as ``lipmap-loc map --lines`` imports them, e.g. DeepLSD's); the detectors'
    lines go through the same length filter (the preset's, or the default preset's 15 px at 640x480)."""
    from lipmap.lines2d import confs, detect_lines_image, get_conf, list_names, load_lines

    if name in confs:
        conf = get_conf(name)
        return lambda view, image: detect_lines_image(image, conf)[0]
    if name.endswith((".h5", ".hdf5")):
        path = Path(name)
        if not path.is_file():
            raise SystemExit(f"lines file {path} does not exist")
        have = set(list_names(path))

        def read(view, image):
            if view.name not in have:
                raise SystemExit(f"{path} has no lines for image {view.name}")
            return length_filter(load_lines(path, view.name), view.camera.width, view.camera.height)

        return read
    if name not in ("edlines", "fld"):
        raise SystemExit(f"unknown detector {name!r}: choose from {', '.join([*confs, 'edlines', 'fld'])} "
                         "or give an HDF5 file of lines (.h5)")
    raw = contrib_detector(name)
    return lambda view, image: length_filter(raw(image), image.shape[1], image.shape[0])


def length_filter(lines: np.ndarray, width: int, height: int) -> np.ndarray:
    """The default LSD preset's length filter and cap, for lines (N, 4) of other detectors."""
    from lipmap.lines2d import filter_lines, get_conf

    base = get_conf("lsd")
    return filter_lines(lines, np.zeros(len(lines)), base.min_length_for(width, height), base.max_lines)[0]


def lift_to_planes(det: np.ndarray, view, caster, n: int = 5, tol: float = 0.01):
    """3D segments (N, 2, 3) of the detections (N, 4) on the planes, and which of them are on one 3D line: all ``n``
    samples (5 % to 95 % along) hit a plane and the middle one lies within ``tol`` metres of the end samples' chord."""
    from lipmap.mapping.assign import pixel_rays_world

    t = np.linspace(0.05, 0.95, n)
    pix = det[:, None, :2] * (1 - t)[None, :, None] + det[:, None, 2:] * t[None, :, None]
    # detections are in COLMAP coordinates (pixel centres at +0.5); pixel_rays_world takes pixel indices
    o, d = pixel_rays_world(pix.reshape(-1, 2) - 0.5, view.cam_from_world, view.camera)
    k, dist = caster.first_hit(o, d)
    X = (o + np.where(np.isfinite(dist), dist, 0.0)[:, None] * d).reshape(len(det), n, 3)
    ok = (k.reshape(len(det), n) >= 0).all(1)
    a, b, mid = X[:, 0], X[:, -1], X[:, n // 2]
    chord = np.linalg.norm(b - a, axis=1)
    off = np.linalg.norm(np.cross(mid - a, b - a), axis=1) / np.maximum(chord, 1e-9)
    return np.stack([a, b], 1), ok & (chord > 1e-6) & (off < tol)


def measure(detect, views, images: dict, caster, gaps) -> dict:
    """Per gap: angle, distance of the nearest re-detection and the source's length (px) for every visible pair."""
    from lipmap import geometry as geo

    by_view = {v.name: np.asarray(detect(v, images[v.name]), dtype=np.float64).reshape(-1, 4) for v in views}
    out = {g: {"angle": [], "dist": [], "length": []} for g in gaps}
    for i, a in enumerate(views):
        det = by_view[a.name]
        if not len(det):
            continue
        segs, ok = lift_to_planes(det, a, caster)
        segs, length = segs[ok], geo.segment_lengths(det[ok])
        for g in gaps:
            if i + g >= len(views) or not len(segs):
                continue
            b = views[i + g]
            proj, valid = geo.project_segments(segs, b.cam_from_world, b.camera)
            clipped, inside = geo.clip_segments_to_image(np.where(valid[:, None, None], proj, 0.0), b.camera.width,
                                                         b.camera.height)
            long_enough = valid & inside & (np.linalg.norm(clipped[:, 1] - clipped[:, 0], axis=1) >= 15)
            idx, ang, dist = nearest_in_view(segs, np.flatnonzero(long_enough), b, by_view[b.name], caster)
            out[g]["angle"].append(ang)
            out[g]["dist"].append(dist)
            out[g]["length"].append(length[idx])
    n_det = np.array([len(x) for x in by_view.values()])
    lengths = np.concatenate([geo.segment_lengths(x) for x in by_view.values()])
    pairs = {g: {k: np.concatenate(v) if v else np.zeros(0) for k, v in d.items()} for g, d in out.items()}
    return {"detections_per_view": float(n_det.mean()), "median_length_px": float(np.median(lengths)),
            "pairs": pairs}


def share(p: dict, angle: float, dist: float, mask=None) -> float:
    hit = (p["angle"] < angle) & (p["dist"] < dist)
    if mask is not None:
        hit = hit[mask]
    return float(hit.mean()) if len(hit) else float("nan")


def pct(v: float) -> str:
    return f"{100 * v:.1f} %" if np.isfinite(v) else "-"  # "-": no such pair (e.g. no short lines in a preset)


def plot(figures: dict, path: Path, scene: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    labels = [f"{a:g} rad\n{d:g} px" for a, d in GATES]
    for name, f in figures.items():
        ax.plot(range(len(GATES)), [100 * f["next_view"][k] for k in f["next_view"]], marker="o", label=name)
    ax.set_xticks(range(len(GATES)), labels)
    ax.axvline(0, color="0.7", lw=0.8, ls="--")
    ax.text(0.05, 2, "the paper's track test", color="0.4", fontsize=8)
    ax.set_ylim(0, 100)
    ax.set_ylabel("% found again in the next mapping view")
    ax.set_xlabel("angle / distance gate")
    ax.set_title(f"{scene}: 2D line repeatability (planes and poses of the map)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None):
    import cv2

    from lipmap.datasets import load_scene
    from lipmap.linemap import LineMap
    from lipmap.mapping.assign import PlaneRaycaster

    ap = results.scene_parser(__doc__)
    ap.add_argument("--detectors", default="lsd,lsd-dense,lsd-long", help="comma-separated detector names")
    ap.add_argument("--gaps", default="1,2,3", help="compare each mapping view with the views this many places on")
    ap.add_argument("--tag", default="", help="suffix of the results file name")
    ap.add_argument("--label", default="", help="added to each row's detector name (e.g. the poses the map was made with)")
    args = ap.parse_args(argv)
    gaps = sorted({int(g) for g in args.gaps.split(",")})
    if not gaps or gaps[0] < 1:
        raise SystemExit(f"--gaps must be positive integers, got {args.gaps!r}")
    detectors = {name: detector(name) for name in args.detectors.split(",")}
    lm = LineMap.load(args.out / "linemap.h5")
    if not lm.planes or "corners" not in lm.planes:
        raise SystemExit(f"{args.out / 'linemap.h5'} has no planes: give the folder of a --method lipmap map")
    scene = load_scene(args.dataset, args.root, args.scene, pose_source=lm.metadata.get("pose_source", "posetxt"))
    views = scene.mapping
    images = {}
    for v in views:
        img = cv2.imread(str(v.color_path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"cannot read image {v.color_path}")
        images[v.name] = img
    caster = PlaneRaycaster(lm.planes["corners"])
    first = gaps[0]
    header = ["detector", "detections per view", "median length px", f"(detection, view +{first}) pairs",
              *(f"found within {a:g} rad / {d:g} px" for a, d in GATES),
              *(f"at 0.01 rad / 2 px, view +{g}" for g in gaps[1:]),
              *(f"at 0.01 rad / 2 px, {lo}-{hi:g} px long" if np.isfinite(hi) else f"at 0.01 rad / 2 px, >= {lo} px long"
                for lo, hi in LENGTH_BINS)]
    rows, figures = [], {}
    for name, detect in detectors.items():
        m = measure(detect, views, images, caster, gaps)
        p = m["pairs"][first]
        f = {"detections_per_view": m["detections_per_view"], "median_length_px": m["median_length_px"],
             "pairs": int(len(p["angle"])),
             "next_view": {f"{a:g} rad / {d:g} px": share(p, a, d) for a, d in GATES},
             "paper_gate_by_gap": {str(g): share(m["pairs"][g], *GATES[0]) for g in gaps},
             "paper_gate_by_length": {f"{lo}-{hi:g}": share(p, *GATES[0], (p["length"] >= lo) & (p["length"] < hi))
                                      for lo, hi in LENGTH_BINS}}
        figures[name] = f
        rows.append([f"{name} ({args.label})" if args.label else name, f"{f['detections_per_view']:.0f}", f"{f['median_length_px']:.0f}", f["pairs"],
                     *(pct(v) for v in f["next_view"].values()),
                     *(pct(f["paper_gate_by_gap"][str(g)]) for g in gaps[1:]),
                     *(pct(v) for v in f["paper_gate_by_length"].values())])
        print(" | ".join(map(str, rows[-1])), flush=True)
    name = f"line-repeatability-{args.scene}" + (f"-{args.tag}" if args.tag else "")
    png = plot(figures, results.RESULTS / f"{name}.png", args.scene)
    results.write(name, {"scene": args.scene, "map": str(args.out / "linemap.h5"), "gaps": gaps, "figures": figures,
                         "picture": png.name, "table": {"header": header, "rows": rows}})


if __name__ == "__main__":
    main()
