"""The share of queries localized within each translation error, per line map: where a median hides the
difference (a median that falls among half-rescued queries moves by cm from one set of draws to the next).

    python benchmarks/localization_cdf.py --name NAME 'LABEL=localization-variants-....json[:VARIANT][+...]' ... [--title T]

Each curve is the point+line result of one variant (default ``default``) of a ``localization_variants.py`` results
file (which keeps every localization's error), or of several joined by ``+`` (pooled: other draws of the same
queries); the point-only curve comes from the first curve's files. Writes
``benchmarks/results/NAME.png`` and ``NAME.json`` (median and the share within 1, 2, 5, 10 and 20 cm per curve).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

THRESHOLDS_CM = (1, 2, 5, 10, 20)
HEADER = ["curve", "localizations", "median cm", *(f"% within {t} cm" for t in THRESHOLDS_CM)]


def load_curve(spec: str) -> tuple[str, dict]:
    """``LABEL=FILE[:VARIANT][+FILE[:VARIANT]...]`` -> (label, the ``t_cm`` dict: point / point+line arrays, the
    files' localizations pooled: draws of other seeds, say)."""
    label, sep, rest = spec.partition("=")
    if not sep:
        raise SystemExit(f"{spec!r}: expected LABEL=FILE[:VARIANT]")
    parts = [_load_part(p) for p in rest.split("+")]
    return label, {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _load_part(part: str) -> dict:
    path, _, variant = part.partition(":")
    path = Path(path) if Path(path).exists() else results.RESULTS / path
    data = json.loads(path.read_text())
    v = data["variants"].get(variant or "default")
    if v is None or "t_cm" not in v:
        raise SystemExit(f"{path}: no per-query errors for variant {variant or 'default'!r} "
                         "(made before localization_variants.py kept them: run it again)")
    return {k: np.asarray(x, dtype=float) for k, x in v["t_cm"].items()}


def row(label: str, t: np.ndarray) -> list:
    med = float(np.median(t))
    return [label, len(t), f"{med:.2f}" if np.isfinite(med) else "failed",
            *(f"{100 * np.mean(t <= c):.1f}" for c in THRESHOLDS_CM)]


def plot(curves: list, path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    x = np.logspace(-1, 2.5, 400)
    for label, t in curves:
        ax.plot(x, [np.mean(t <= v) for v in x], label=f"{label} (median {np.median(t):.1f} cm)"
                if np.isfinite(np.median(t)) else f"{label} (median: no pose)")
    for c in (1, 2, 5):
        ax.axvline(c, color="0.8", lw=0.8, zorder=0)
    ax.axhline(0.5, color="0.6", lw=0.8, ls="--", zorder=0)
    ax.set_xscale("log")
    ax.set_xlabel("translation error (cm)")
    ax.set_ylabel("share of localizations within")
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--name", required=True, help="results file name (without extension)")
    ap.add_argument("--title", default="")
    ap.add_argument("curves", nargs="+", help="LABEL=FILE[:VARIANT]")
    args = ap.parse_args(argv)
    loaded = [load_curve(s) for s in args.curves]
    curves = [("point-only", loaded[0][1]["point"])] + [(label, t["point+line"]) for label, t in loaded]
    rows = [row(label, t) for label, t in curves]
    print("\n".join("| " + " | ".join(map(str, r)) + " |" for r in [HEADER, *rows]))
    png = plot(curves, results.RESULTS / f"{args.name}.png", args.title)
    results.write(args.name, {"curves": args.curves, "picture": png.name, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
