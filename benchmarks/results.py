"""The one home of benchmark figures: each benchmark script writes its measurements to
``benchmarks/results/<name>.json`` with their provenance (command, commit, machine, date); the tables of the
README and docs/*.md are generated from these files by ``benchmarks/readme_tables.py``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
REPO = RESULTS.parents[1]


def scene_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments of every per-scene benchmark: the dataset, its root, the scene and the output folder."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True, choices=["7scenes", "synthetic"])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--out", type=Path, required=True)
    return ap


def _git(*args) -> str:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


THREAD_ENV = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
# environment variables that change what a run computes or how fast, recorded with its machine
RECORDED_ENV = THREAD_ENV + ("LIPMAP_RENDER_BACKEND",)


def machine() -> dict:
    """CPU model and cores, memory, GPU (if torch sees one), Python and torch versions, torch's threads and the
    thread environment variables that were set."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        kb = int(next(l for l in Path("/proc/meminfo").read_text().splitlines() if l.startswith("MemTotal")).split()[1])
        mem_gb = round(kb / 2**20, 1)
    except (OSError, StopIteration, ValueError):
        pass
    out = {"cpu": cpu, "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
           "memory_gb": mem_gb, "python": platform.python_version(), "gpu": None}
    try:
        import torch

        out["torch"] = torch.__version__
        out["torch_threads"] = torch.get_num_threads()
        if torch.cuda.is_available():
            out["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    # thread settings change timings severalfold: PASSIVE is slower alone, spinning far slower beside a busy process;
    # the renderer backend changes the map at the float level
    env = {k: os.environ[k] for k in RECORDED_ENV if k in os.environ}
    if env:
        out["env"] = env
    return out


# placeholders for the folders of one machine in a recorded command: the option names what the folder holds
_PLACEHOLDERS = {"--root": "DATA", "--out": "OUT"}


def portable_path(path: str, placeholder: str = "WORK", keep: int = 1) -> str:
    """``path`` relative to the repository when in it or in the shared data beside it, else ``placeholder`` plus its
    last ``keep`` components (a folder of this machine means nothing elsewhere)."""
    p = Path(path)
    for base, prefix in ((REPO, ""), (REPO.parent / "shared", "../shared/")):
        try:
            rel = p.resolve().relative_to(base.resolve()).as_posix()
            return prefix + rel if rel != "." else (prefix.rstrip("/") or ".")
        except ValueError:
            continue
    return "/".join([placeholder, *p.parts[-keep:]])


def _portable_values(obj):
    """``obj`` with every absolute path among its strings made portable (:func:`portable_path`)."""
    if isinstance(obj, dict):
        return {k: _portable_values(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_portable_values(v) for v in obj]
    if isinstance(obj, str) and obj.startswith("/") and " " not in obj and "\n" not in obj:
        return portable_path(obj, keep=3)
    return obj


def portable_args(args: list) -> list:
    """``args`` with this machine's folders written portably: paths in the repository or the shared data beside it
    relative to the repository, any other absolute path as DATA/, OUT/ or WORK/ plus its last component."""
    import re

    out = []
    for i, a in enumerate(args):
        opt = a.partition("=")[0] if a.startswith("--") else (args[i - 1] if i else "")
        name = _PLACEHOLDERS.get(opt, "WORK")
        # an absolute path alone, after --opt=, or in a list of name=path or a,b values
        out.append(re.sub(r"(^|[=,])(/[^=,\s]+)", lambda m: m.group(1) + portable_path(m.group(2), name), a))
    return out


def provenance(argv=None) -> dict:
    argv = sys.argv if argv is None else argv
    script = Path(argv[0])
    try:
        script = script.resolve().relative_to(REPO)
    except ValueError:
        pass
    return {"command": "python " + " ".join(shlex.quote(a) for a in [str(script), *portable_args(list(argv[1:]))]),
            "commit": _git("rev-parse", "--short", "HEAD"), "dirty": dirty(),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "machine": machine()}


# set to 1 to write figures measured on a tree with uncommitted changes (marked so; no README table takes them)
ALLOW_DIRTY_ENV = "LIPMAP_BENCH_ALLOW_DIRTY"
_DEFAULT_RESULTS = RESULTS


# what benchmark runs write themselves: a series of runs from one commit stays clean
_NOT_CODE = ("benchmarks/results", "README.md", "docs")


def _code_status(*opts: str) -> str:
    """``git status`` of the tracked files outside :data:`_NOT_CODE`."""
    return _git("status", *opts, "--untracked-files=no", "--", ".", *(f":!{p}" for p in _NOT_CODE))


def dirty() -> bool:
    """Whether the checkout has uncommitted changes to tracked files (figures from it reproduce from no commit);
    the figures already written into ``benchmarks/results/`` and the documents generated from them do not count."""
    return bool(_code_status("--porcelain"))


def foreign_packages() -> list[str]:
    """The project's packages already imported from outside this checkout (another checkout's editable install):
    figures measured with them would be recorded under this checkout's commit."""
    out = []
    for name in ("lipmap", "localization"):
        mod = sys.modules.get(name)
        where = Path(getattr(mod, "__file__", None) or "").resolve().parent if mod else None
        if where is not None and where != REPO / name:
            out.append(f"{name} from {where}")
    return out


def require_clean() -> None:
    """Stop a benchmark that would write into ``benchmarks/results/`` from a dirty tree, or with the project's code
    imported from another checkout, before it spends its time (unless ``LIPMAP_BENCH_ALLOW_DIRTY=1``)."""
    foreign = foreign_packages() if RESULTS == _DEFAULT_RESULTS else []
    if foreign:
        raise SystemExit(f"benchmarks/results: {', '.join(foreign)}, not this checkout ({REPO}), so the figures would "
                         f"not come from its commit. Install this checkout (pip install -e .) or run with "
                         f"PYTHONPATH={REPO}.")
    if RESULTS == _DEFAULT_RESULTS and os.environ.get(ALLOW_DIRTY_ENV) != "1" and dirty():
        raise SystemExit(f"benchmarks/results: the tree has uncommitted changes, so these figures would reproduce from no "
                         f"commit. Commit first (or run from a clean worktree), or set {ALLOW_DIRTY_ENV}=1 to write "
                         f"them marked '(uncommitted changes)'.\n{_code_status('--short')}")


def write(name: str, data: dict, argv=None) -> Path:
    """Write ``data`` with its provenance to ``benchmarks/results/<name>.json``; returns the path. Refuses a dirty
    tree (:func:`require_clean`)."""
    require_clean()
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    data = _portable_values(json.loads(json.dumps(data, default=float)))
    path.write_text(json.dumps({"provenance": provenance(argv), **data}, indent=1, default=float) + "\n")
    print(f"results: {path}")
    return path


def read(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text())


def names(prefix: str = "") -> list[str]:
    return sorted(p.stem for p in RESULTS.glob(f"{prefix}*.json"))


def variants_run(data: dict) -> str:
    """What a ``localization_variants.py`` result measured, for its tables' ``run`` column: scene (ground truth), line
    map, point matches per query and draws."""
    import shlex

    args = shlex.split(data["provenance"]["command"])
    pose = args[args.index("--pose-source") + 1] if "--pose-source" in args[:-1] else "posetxt"
    m, draws = str(data["matches"]), len(data.get("match_seeds") or [])
    budget = "all matches" if m in ("0", "all", "None") else f"{m} matches, {draws} draws"
    return f"{data['scene']} ({pose}), {data['method']}, {budget}"
