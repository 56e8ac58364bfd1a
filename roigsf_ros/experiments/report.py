"""``roigsf bench`` report: markdown tables (paper Tables I/III/IV shape) and matplotlib plots (Agg).

Files (each written atomically): ``results.md``; ``quality_vs_views.png`` (pool: test PSNR and
mesh recall / F-score at 5 cm against the number of views, mean +- std over seeds; stream: the
same metrics against the number of keyframes, one point per policy); ``chosen_views.png`` (the
trajectory top-down in XY with the chosen views of seed 0, one panel per policy);
``uncertainty_<label>.png`` (for a few held-out views of seed 0: image, |depth error|, Eq. 17
uncertainty, FisherRF's colour-Fisher map, with each map's normalised / raw AUSE and Spearman rho).
The bench writes them, with results.json, into a temporary folder that becomes the output folder once complete.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

from roigsf_ros.core.fileio import atomic_path

TABLE_COLUMNS = (
    ("#views", "n_keyframes", "{:.1f}"),
    ("PSNR", "psnr", "{:.2f}"),
    ("SSIM", "ssim", "{:.3f}"),
    ("Depth L1 (cm)", "depth_l1_cm", "{:.2f}"),
    ("PSNR test scene", "test_scene_psnr", "{:.2f}"),
    ("Depth L1 (cm) test scene", "test_scene_depth_l1_cm", "{:.2f}"),
    ("Error share in holes, test scene", "test_scene_uncovered_error_share", "{:.2f}"),
    ("Holes on surface no keyframe saw, test scene", "test_scene_holes_unseen_share", "{:.2f}"),
    ("P@1cm", "precision@1cm", "{:.3f}"),
    ("R@1cm", "recall@1cm", "{:.3f}"),
    ("F@1cm", "fscore@1cm", "{:.3f}"),
    ("P@5cm", "precision@5cm", "{:.3f}"),
    ("R@5cm", "recall@5cm", "{:.3f}"),
    ("F@5cm", "fscore@5cm", "{:.3f}"),
    ("AUSE norm. Eq.17", "ause_eq17", "{:.3f}"),
    ("AUSE norm. FisherRF", "ause_fisherrf", "{:.3f}"),
    ("raw AUSE (cm) Eq.17", "ause_raw_eq17_cm", "{:.2f}"),
    ("raw AUSE (cm) FisherRF", "ause_raw_fisherrf_cm", "{:.2f}"),
    ("raw AUSE (cm) random", "ause_raw_random_cm", "{:.2f}"),
    ("rho Eq.17", "rho_eq17", "{:.2f}"),
    ("rho FisherRF", "rho_fisherrf", "{:.2f}"),
    ("Wall (s)", "wall_s", "{:.0f}"),
)
"""Columns of the main table: header, summary key, format of the mean."""

AUSE_CAVEAT = (
    "AUSE norm. divides the area by the joint maximum of the two sparsification curves (FisherRF / Bayes' Rays"
    " code), which rewards maps that rank pixels backwards (their curve peaks far above the mean error); read it"
    " with the raw AUSE (cm, lower is better; above the seeded random ordering's = worse than no information) and"
    " Spearman rho (uncertainty vs |depth error| over all pixels alike, while AUSE is driven by the largest errors,"
    " so a small |rho| and AUSE can disagree)."
)
"""The line under the main table."""

CURVE_METRICS = (("test_psnr", "test PSNR (dB)", "{:.2f}"), ("recall@5cm", "recall @5cm", "{:.3f}"),
                 ("fscore@5cm", "F-score @5cm", "{:.3f}"))  # fmt: skip
"""Pool curve metrics: key, axis label, table format."""


def cell(summary_row: dict[str, Any], key: str, fmt: str) -> str:
    """A table cell: the seed mean in ``fmt``, ``+- std`` when there are several seeds, ``-`` when absent."""
    s = summary_row.get(key)
    if s is None or s.get("mean") is None:
        return "-"
    text = fmt.format(s["mean"])
    if s.get("n", 1) > 1 and s.get("std") is not None:
        text += " ± " + fmt.format(s["std"])
    return text


def table_columns(results: dict[str, Any]) -> tuple[tuple[str, str, str], ...]:
    """The main table's columns for these results: the test-scene ones only when the bench had a test scene (a pool
    bench never does: it holds out its own test views), so a table has no column that is empty by construction.
    """
    if results.get("test_scene"):
        return TABLE_COLUMNS
    return tuple(c for c in TABLE_COLUMNS if not c[1].startswith("test_scene_"))


def markdown(results: dict[str, Any]) -> str:
    """``results.md``: the main table (one row per policy, mean over seeds) and, for pool, the curve table."""
    setting = results["setting"]
    seeds = results["seeds"]
    lines = [
        f"# roigsf bench: {setting} setting",
        "",
        f"- scene: `{results['scene']}` ({results['n_frames']} frames at {results['size'][0]}x{results['size'][1]},"
        f" stride {results['stride']})",
        f"- ground-truth mesh: `{results['gt_mesh']}`" if results.get("gt_mesh") else "- no ground-truth mesh",
        f"- seeds: {', '.join(str(s) for s in seeds)} (mean ± population std over {len(seeds)} seed(s))",
        f"- total wall time: {results['wall_s']:.0f} s",
    ]
    if results.get("tf_child_frame_note"):
        lines.append(f"- **TF: {results['tf_child_frame_note']}; every figure is wrong**")
    from roigsf_ros.mapping.mapper import depth_scale_note  # here: torch only where a report is written

    depth_notes = {depth_scale_note(r.get("metrics", {})) for r in results.get("runs", [])} - {""}
    lines += [f"- **{note} (in at least one run)**" for note in sorted(depth_notes)]  # it was said on stderr only
    if results.get("command"):
        lines.append(f"- command: `{results['command']}`")
    if setting == "pool":
        pc = results["pool_config"]
        lines.append(
            f"- pool: {pc['n_views']} views ({pc['n_initial']} initial: first + farthest), test view every "
            f"{pc['test_every']}th frame, pool stride {pc['pool_stride']}, schedule {pc['schedule']}: "
            f"{pc['initial_iters']} initial + {pc['iters_per_view']} per view + {pc['final_iters']} final steps"
        )
        lines.append("- image metrics over the held-out test views; #views = training views")
    else:
        lines.append("- image metrics over the non-keyframes; #views = keyframes")
        if results.get("test_scene"):
            lines.append(
                f"- test scene: `{results['test_scene']}` (frames no policy sees, the same for every run): columns"
                " 'PSNR test scene', 'Depth L1 (cm) test scene', 'Error share in holes, test scene' (the part of"
                " the squared colour error at pixels the map leaves uncovered: alpha < 0.5) and 'Holes on surface no"
                " keyframe saw, test scene' (of those pixels, the share farther than 5 cm from every keyframe's depth:"
                " a matter of which frames were keyframes; the rest the map saw and does not render)"
            )
    lines.append(
        f"- AUSE: pixel uncertainty vs |depth error| on {_ause_views(results)} (lower is better), mean over views"
    )
    rescore = results.get("ause_rescore")
    if rescore:
        lines.append(f"- AUSE study recomputed from the saved maps at {rescore['at']} ({rescore['wall_s']:.0f} s)")
    lines += ["", "## Quality per policy (Tables I / III / IV)", ""]
    columns = table_columns(results)
    lines.append("| Policy | " + " | ".join(c[0] for c in columns) + " |")
    lines.append("|---|" + "---|" * len(columns))
    for p in results["policies"]:
        row = results["summary"].get(p["label"], {})
        lines.append(f"| {p['label']} | " + " | ".join(cell(row, k, f) for _, k, f in columns) + " |")
    lines += ["", AUSE_CAVEAT]
    curves = results.get("curves") or {}
    if setting == "pool" and curves:
        ns = sorted({r["n_views"] for rows in curves.values() for r in rows})
        lines += ["", "## Quality against the number of views", ""]
        lines.append("| Policy | Metric | " + " | ".join(str(n) for n in ns) + " |")
        lines.append("|---|---|" + "---|" * len(ns))
        for p in results["policies"]:
            rows = {r["n_views"]: r for r in curves.get(p["label"], [])}
            for key, label, fmt in CURVE_METRICS:
                cells = [cell(rows.get(n, {}), key, fmt) for n in ns]
                if any(c != "-" for c in cells):
                    lines.append(f"| {p['label']} | {label} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)


def _ause_views(results: dict[str, Any]) -> str:
    """``6 held-out views per run``, with what the runs had where it is fewer: a 4-frame stream has 2 or 3
    non-keyframes to hold out, and the report said 6 (the number asked) for runs scored on 2 and on 3.
    """
    asked = results.get("uncertainty_views", "?")
    runs = [r for r in results.get("runs") or [] if isinstance(r, dict) and "uncertainty_per_view" in r]
    had = {(r.get("label"), len(r["uncertainty_per_view"] or [])) for r in runs}
    if not runs or {n for _, n in had} == {asked}:
        return f"{asked} held-out views per run"
    fewer = ", ".join(f"{label} {n}" for label, n in sorted(had, key=lambda x: (str(x[0]), x[1])) if n != asked)
    return f"{asked} held-out views per run (fewer where a run had fewer to hold out: {fewer})"


def parse_markdown_table(text: str, header_start: str = "| Policy | #views") -> dict[str, dict[str, str]]:
    """The main table of :func:`markdown` back as {policy: {column header: cell text}} (for checks and tools)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    headers = [h.strip() for h in lines[start].strip("|").split("|")]
    out: dict[str, dict[str, str]] = {}
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        out[cells[0]] = dict(zip(headers[1:], cells[1:], strict=True))
    return out


# ---------------------------------------------------------------------------------------- plots
def _save(fig: plt.Figure, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)


def plot_quality(results: dict[str, Any], path: Path) -> None:
    """Quality against #views (pool: curves, mean +- std) or #keyframes (stream: one point per policy)."""
    metrics = [m for m in CURVE_METRICS if m[0] == "test_psnr" or results.get("gt_mesh")]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.5 * len(metrics), 3.6), squeeze=False, layout="constrained")
    for ax, (key, label, _) in zip(axes[0], metrics, strict=True):
        for p in results["policies"]:
            if results["setting"] == "pool":
                rows = [r for r in results["curves"].get(p["label"], []) if r.get(key)]
                if not rows:
                    continue
                n = np.array([r["n_views"] for r in rows])
                mu = np.array([r[key]["mean"] for r in rows])
                sd = np.array([r[key]["std"] for r in rows])
                ax.plot(n, mu, marker="o", ms=3, label=p["label"])
                ax.fill_between(n, mu - sd, mu + sd, alpha=0.2)
            else:
                row = results["summary"].get(p["label"], {})
                skey = "psnr" if key == "test_psnr" else key
                if skey in row and "n_keyframes" in row:
                    ax.errorbar(row["n_keyframes"]["mean"], row[skey]["mean"], xerr=row["n_keyframes"]["std"],
                                yerr=row[skey]["std"], marker="o", capsize=3, label=p["label"])  # fmt: skip
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # views and keyframes are counts: no 2.5 views
        ax.set_xlabel("training views" if results["setting"] == "pool" else "keyframes")
        ax.set_ylabel(label if results["setting"] == "pool" or key != "test_psnr" else "PSNR (dB)")
        ax.grid(alpha=0.3)
    handles, names = axes[0][0].get_legend_handles_labels()
    if handles:  # below the panels: inside the first one it hid a policy's point
        fig.legend(handles, names, loc="outside lower center", ncol=min(len(names), 3), fontsize=7)
    fig.suptitle(f"{results['setting']}: quality vs number of views")
    _save(fig, path)


def plot_chosen_views(results: dict[str, Any], runs: list[dict[str, Any]], path: Path) -> None:
    """Top-down XY trajectory with the views each policy chose (seed 0), one panel per policy."""
    labels = [p["label"] for p in results["policies"]]
    n = len(labels)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.0 * cols, 4.0 * rows), squeeze=False, layout="constrained")
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax, label in zip(axes.flat, labels, strict=False):
        run = next((r for r in runs if r["label"] == label and r["seed"] == 0), None)
        if run is None:
            continue
        traj = np.asarray(run["_trajectory"])
        c = traj[:, :3, 3]
        ax.plot(c[:, 0], c[:, 1], "-", color="0.75", lw=1, zorder=1)
        test = run.get("test_positions") or []
        if test:
            ax.scatter(c[test, 0], c[test, 1], marker="x", s=14, color="0.4", label="test", zorder=2)
        chosen = run["chosen_positions"]
        if chosen:
            sc = ax.scatter(c[chosen, 0], c[chosen, 1], c=np.arange(1, len(chosen) + 1), cmap="viridis", s=22,
                            edgecolors="k", linewidths=0.4, zorder=3, label="chosen")  # fmt: skip
            fwd = traj[chosen, :3, 2]  # optical axes
            ax.quiver(c[chosen, 0], c[chosen, 1], fwd[:, 0], fwd[:, 1], angles="xy", scale=12, width=0.004,
                      color="C3", zorder=4)  # fmt: skip
            bar = fig.colorbar(sc, ax=ax, fraction=0.046, pad=0.02, label="selection order")
            bar.ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # 1st, 2nd, ... pick: no 0.5
        ax.set_title(f"{label}: {len(chosen)} views", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"{results['setting']}: chosen views (seed 0), top-down")
    _save(fig, path)


def plot_uncertainty(label: str, run: dict[str, Any], path: Path) -> bool:
    """Image, |depth error|, Eq. 17 and FisherRF uncertainty of a few held-out views; False if none."""
    maps = run.get("_maps") or []
    if not maps:
        return False
    per = {v["frame"]: v for v in run.get("uncertainty_per_view", [])}
    fig, axes = plt.subplots(len(maps), 4, figsize=(14, 2.9 * len(maps)), squeeze=False)
    for row, m in zip(axes, maps, strict=True):
        v = per.get(m["frame"], {})
        err = np.nan_to_num(m["depth_err_m"], nan=0.0)
        panels = (
            (m["rgb"], f"frame {m['frame']}", None),
            (err * 100.0, "|depth error| (cm)", "magma"),
            (m["u_eq17"], f"Eq. 17 U: {_ause_title(v, 'eq17')}", "magma"),
            (m["u_fisherrf"], f"FisherRF: {_ause_title(v, 'fisherrf')}", "magma"),
        )
        for ax, (img, title, cmap) in zip(row, panels, strict=True):
            if cmap is None:
                ax.imshow(img)
            else:
                hi = float(np.percentile(img, 99)) if np.any(img > 0) else 1.0
                im = ax.imshow(img, cmap=cmap, vmin=0.0, vmax=max(hi, 1e-12))
                plt.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.suptitle(f"{label} (seed 0): uncertainty vs depth error on held-out views")
    _save(fig, path)
    return True


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _ause_title(view: dict[str, Any], name: str) -> str:
    """Two title lines for one map of one view: normalised AUSE; raw AUSE (cm) vs random, Spearman rho."""
    raw, rnd = view.get(f"ause_raw_{name}"), view.get("ause_raw_random")
    cm = "-" if raw is None else f"{100 * raw:.2f}"
    rand = "-" if rnd is None else f"{100 * rnd:.2f}"
    rho = "-" if view.get(f"rho_{name}") is None else f"{view[f'rho_{name}']:.2f}"
    return f"AUSE norm. {_f(view.get(f'ause_{name}'))}\nraw {cm} cm (random {rand}), rho {rho}"


REPORT_FILES = ("results.md", "quality_vs_views.png", "chosen_views.png", "uncertainty_*.png")
"""Names (glob patterns) of the files :func:`write_report` may write: those a rescore of the AUSE study replaces."""


def write_report(out: Path, results: dict[str, Any], runs: list[dict[str, Any]]) -> list[Path]:
    """Write results.md and every plot into ``out`` (atomically each; see :data:`REPORT_FILES`); returns them."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(markdown(results))
    written.append(out / "results.md")
    plot_quality(results, out / "quality_vs_views.png")
    plot_chosen_views(results, runs, out / "chosen_views.png")
    written += [out / "quality_vs_views.png", out / "chosen_views.png"]
    for p in results["policies"]:
        run = next((r for r in runs if r["label"] == p["label"] and r["seed"] == 0), None)
        name = "".join(c if c.isalnum() or c in "-_." else "_" for c in p["label"])
        if run is not None and plot_uncertainty(p["label"], run, out / f"uncertainty_{name}.png"):
            written.append(out / f"uncertainty_{name}.png")
    return written


__all__ = ["AUSE_CAVEAT", "TABLE_COLUMNS", "markdown", "parse_markdown_table", "table_columns", "write_report"]
