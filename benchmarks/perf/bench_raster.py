"""Plane renderer speed: forward + backward of one training iteration, one JSON line per configuration.

    python benchmarks/perf/bench_raster.py                # CPU (2 threads), CUDA too when present
    python benchmarks/perf/bench_raster.py --quick        # 320x240 / 2000 planes only

Renderers (``--backends``, default ``baseline,torch,warp``; the ``renderer`` column): ``warp`` the fused
kernels (:mod:`lipmap.planes.raster_warp`, the ``fast`` extra), ``torch`` this checkout's torch backend, and
``baseline`` the torch renderer as it was before the fused one (``lipmap/planes/render.py`` at
``--baseline-rev``, read with ``git show``), timed in the same run so that the speed-ups are measured on one
machine under one load. Each configuration runs in a fresh process, the renderers one after the other.

Planes: initialized from the real RedKitchen depth (``../shared/data/7scenes-redkitchen-mini``,
TSDF + decimation to N faces, exactly as the pipeline does; the ``source`` field says
``redkitchen-init``) and rendered from a mapping camera; without that data, a seeded random box
room (``source: box-room``: planes on the walls/floor/ceiling of a 5 x 4 x 2.7 m room, 3-15 cm
radii, seen from inside). Init planes have small radii (0.3 x the face size); ``--grow`` scales
them (default 2.5, about the coverage after optimization; ``grow`` is printed).

Timed: ``rasterize_planes`` (selection + differentiable compositing) and ``backward`` of an L1
depth + normal loss, median of ``--repeat`` runs after ``--warmup`` (the warm-up also compiles the Warp
kernels when their cache is empty). ``lambda`` is the splat
sharpness: 1500 is the value for the last ~60 % of a training run, 300 the early part (the
reference schedule starts at 37, where splats reach 27 cm beyond each rectangle and the cost grows
several-fold; run ``--lam 37`` to see it).

Peak memory: CUDA ``torch.cuda.max_memory_allocated`` (reset per configuration); CPU: peak
resident set size during warm-up + timed runs minus the resident size just before them, in a
fresh subprocess per configuration (Linux: the peak ``VmHWM`` is reset by writing 5 to
``/proc/self/clear_refs``; where that is not possible it falls back to the growth of
``resource.getrusage(...).ru_maxrss``, which under-reports when loading the scene peaked higher).

On a shared machine, a busy core makes torch's 2-thread OpenMP pool spin: one measurement went
from 40 ms to 3.3 s. ``OMP_WAIT_POLICY=PASSIVE`` kept it at 61 ms under the same load.

Results go to ``benchmarks/results/perf-raster.json`` (with command, commit, machine and date); the
docs/performance.md's renderer figures are generated from there.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]
BASELINE_REV = "5c648aa"  # the last commit whose renderer is the torch one the fused kernels replace
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402
DATA = (REPO / ".." / "shared" / "data" / "7scenes-redkitchen-mini").resolve()


def box_room(K: int, seed: int = 0):
    from lipmap.planes import Planes
    from lipmap.poses import make_T

    rng = np.random.default_rng(seed)
    L = np.array([5.0, 4.0, 2.7])
    faces, areas = [], []
    for ax in range(3):
        o = [i for i in range(3) if i != ax]
        for side in (0, 1):
            faces.append((ax, side))
            areas.append(L[o[0]] * L[o[1]])
    f = rng.choice(6, K, p=np.array(areas) / sum(areas))
    c = rng.random((K, 3)) * L
    n = np.zeros((K, 3))
    for i, (ax, side) in enumerate(faces):
        m = f == i
        c[m, ax] = side * L[ax]
        n[m, ax] = 1.0 if side == 0 else -1.0
    n += rng.normal(0, 0.02, n.shape)
    p = Planes.from_normals(c - L / 2, n, np.ones(K))
    p.radii = torch.tensor(rng.uniform(0.03, 0.15, (K, 4)), dtype=torch.float32)
    eye, target = np.array([-1.5, -1.2, 0.0]), np.array([2.5, 2.0, -0.3])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return p, make_T(R, -R @ eye), (525.0, 525.0, 320.0, 240.0)


def kitchen(K: int, grow: float):
    from lipmap.datasets import load_scene
    from lipmap.planes.init import PlaneInitConfig, init_planes

    scene = load_scene("7scenes", DATA, "redkitchen")
    views = scene.mapping[::5]
    cache = Path(os.environ.get("TMPDIR", "/tmp")) / f"lipmap_bench_kitchen_{K}.pt"
    if cache.exists():
        p = torch.load(cache)
        from lipmap.planes import Planes

        planes = Planes(*p)
    else:
        planes = init_planes(views, PlaneInitConfig(n_planes=K, voxel_size=0.02))
        torch.save(planes.tensors(), cache)
    planes.radii = planes.radii * grow
    v = scene.mapping[3]
    return planes, v.cam_from_world, v.camera.params


def _status_kib(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def _reset_peak_rss() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def baseline_renderer(rev: str = BASELINE_REV):
    """``rasterize_planes`` of ``lipmap/planes/render.py`` at commit ``rev``, loaded beside today's package."""
    import importlib.util

    src = subprocess.run(["git", "show", f"{rev}:lipmap/planes/render.py"], cwd=REPO, capture_output=True, text=True,
                         check=True).stdout
    name = "lipmap.planes._render_baseline"
    spec = importlib.util.spec_from_loader(name, loader=None)
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "lipmap.planes"  # its relative imports (primitives, errors) resolve in today's package
    sys.modules[name] = mod
    exec(compile(src, f"{rev}:lipmap/planes/render.py", "exec"), mod.__dict__)
    return mod.rasterize_planes


def renderer(backend: str, baseline_rev: str = BASELINE_REV):
    """``rasterize_planes(center, quat, radii, T, intrinsics, W, H, lam)`` of one backend."""
    if backend == "baseline":
        return baseline_renderer(baseline_rev)
    from lipmap.planes import rasterize_planes

    return lambda *a: rasterize_planes(*a, backend=backend)


def training_step(res: str, K: int, device: str, lam: float, grow: float = 2.5, box: bool = False,
                  backend: str = "auto", baseline_rev: str = BASELINE_REV):
    """``(step, source)``: one forward + backward of the renderer (L1 depth + normal loss against a flat target) at
    ``res`` ("WxH") over ``K`` planes on ``device``; ``source`` says which planes (see the module docstring)."""
    rasterize_planes = renderer(backend, baseline_rev)

    W, H = (int(x) for x in res.split("x"))
    if DATA.is_dir() and not box:
        planes, T, intr = kitchen(K, grow)
        source = "redkitchen-init"
    else:
        planes, T, intr = box_room(K)
        source = "box-room"
    s = W / 640.0
    intr = tuple(float(x) * s for x in intr)
    dev = torch.device(device)
    planes = planes.to(dev)
    T = torch.as_tensor(T, dtype=torch.float32, device=dev)
    params = [t.clone().requires_grad_(True) for t in planes.tensors()]
    target_d = torch.full((H, W), 2.0, device=dev)
    target_n = torch.zeros(H, W, 3, device=dev)
    target_n[..., 2] = -1

    def step():
        out = rasterize_planes(*params, T, intr, W, H, lam)
        loss = (out.depth - target_d).abs().mean() + (out.normal - target_n).abs().sum(-1).mean()
        loss.backward()
        return out

    return step, source


def run_one(args, res: str, K: int, device: str, backend: str) -> dict:
    torch.set_num_threads(args.threads)
    step, source = training_step(res, K, device, args.lam, args.grow, args.box, backend, args.baseline_rev)
    dev = torch.device(device)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    if backend == "warp":  # load (or compile) the kernel module before the memory baseline: it is not the step's
        renderer("warp")(*(torch.zeros(1, n, device=dev) for n in (3, 4, 4)), torch.eye(4, device=dev),
                         (10.0, 10.0, 4.0, 4.0), 8, 8, 300.0)
    if dev.type == "cuda":
        sync()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    hwm_reset = _reset_peak_rss()
    rss0 = _status_kib("VmRSS") if hwm_reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for _ in range(args.warmup):
        step()
    sync()
    times = []
    for _ in range(args.repeat):
        sync()
        t0 = time.perf_counter()
        out = step()
        sync()
        times.append(time.perf_counter() - t0)
    if dev.type == "cuda":
        peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    else:
        peak_kib = _status_kib("VmHWM") if hwm_reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak = (peak_kib - rss0) / 1024
    try:
        import warp

        warp_version = warp.config.version
    except ImportError:
        warp_version = None
    return {
        "resolution": res,
        "planes": K,
        "renderer": backend if backend != "baseline" else f"baseline {args.baseline_rev}",
        "device": device if device == "cpu" else torch.cuda.get_device_name(0),
        "ms_per_iter": round(1000 * float(np.median(times)), 1),
        "ms_min": round(1000 * float(np.min(times)), 1),
        "peak_mb": round(float(peak), 1),
        "threads": args.threads if device == "cpu" else None,
        "lambda": args.lam,
        "pairs": int((out.hits >= 0).sum()),
        "source": source,
        "grow": args.grow if source == "redkitchen-init" else None,
        "torch": torch.__version__,
        "warp": warp_version if backend == "warp" else None,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--lam", type=float, default=None, help="one lambda (default: 1500 and 300)")
    ap.add_argument("--grow", type=float, default=2.5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--box", action="store_true", help="use the random box room even if the real data is there")
    ap.add_argument("--devices", default=None, help="comma list (default: cpu, and cuda when available)")
    ap.add_argument("--backends", default="baseline,torch,warp",
                    help="comma list of renderers: baseline (the torch renderer at --baseline-rev), torch, warp")
    ap.add_argument("--baseline-rev", default=BASELINE_REV)
    ap.add_argument("--tag", default=None, help="suffix of the results name (perf-raster[-quick]-TAG)")
    ap.add_argument("--one", nargs=4, metavar=("RES", "K", "DEVICE", "BACKEND"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:  # child process: one configuration
        res, K, device, backend = args.one
        print(json.dumps(run_one(args, res, int(K), device, backend)), flush=True)
        return
    devices = args.devices.split(",") if args.devices else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    resolutions = ["320x240"] if args.quick else ["320x240", "640x480"]
    counts = [2000] if args.quick else [2000, 10000]
    lams = [args.lam] if args.lam is not None else [1500.0, 300.0]
    backends = args.backends.split(",")
    records = []
    for device in devices:
        for lam in lams:
            for res in resolutions:
                for K in counts:
                    for backend in backends:
                        cmd = [sys.executable, __file__, "--one", res, str(K), device, backend, "--lam", str(lam),
                               "--threads", str(args.threads), "--grow", str(args.grow), "--warmup", str(args.warmup),
                               "--repeat", str(args.repeat), "--baseline-rev", args.baseline_rev]
                        cmd += ["--box"] if args.box else []
                        r = subprocess.run(cmd, capture_output=True, text=True)
                        line = [l for l in r.stdout.splitlines() if l.startswith("{")]
                        if r.returncode != 0 or not line:
                            rec = {"resolution": res, "planes": K, "device": device, "lambda": lam, "renderer": backend,
                                   "error": r.stderr.strip().splitlines()[-1:]}
                        else:
                            rec = json.loads(line[-1])
                        print(json.dumps(rec), flush=True)
                        records.append(rec)
    header = ["resolution", "planes", "lambda", "renderer", "device", "ms per forward+backward (median)", "peak MB",
              "pixel-plane pairs"]
    rows = [[r["resolution"], r["planes"], f"{r['lambda']:g}", r.get("renderer", ""),
             r["device"] + (f", {r['threads']} threads" if r.get("threads") else ""),
             r.get("ms_per_iter", "error"), r.get("peak_mb", ""), r.get("pairs", "")] for r in records]
    name = "perf-raster" + ("-quick" if args.quick else "") + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"records": records, "table": {"header": header, "rows": rows}})


if __name__ == "__main__":
    main()
