"""Human-facing views of an :func:`~terrainmap.evaluation.accuracy.evaluate` report: a text table and a plot."""

from __future__ import annotations

from pathlib import Path

from .scores import METRICS

HEADERS = {
    "elevation_rmse_m": "rmse_m", "elevation_mae_m": "mae_m", "elevation_bias_m": "bias_m",
    "elevation_p95_m": "p95_m", "slope_error_median_deg": "slope°", "coverage": "cover",
    "terrain_precision": "prec", "terrain_recall": "recall", "terrain_f1": "f1",
    "obstacle_recall": "obs_rec", "false_obstacles_per_frame": "false/fr",
}
"""Short column titles of the table, one per metric."""


def _cell(metric: str, value: float | None) -> str:
    if value is None:
        return "—"
    return f"{value:.2f}" if metric in ("slope_error_median_deg", "false_obstacles_per_frame") else f"{value:.3f}"


def format_table(report: dict) -> str:
    """Methods × metrics, one block per range band, as plain text."""
    methods = report["methods"]
    width = max(len(m) for m in methods) if methods else 6
    header = f"{'method':<{width}} " + " ".join(f"{HEADERS[m]:>8}" for m in METRICS)
    failed = ", ".join(f"{reason} ×{n}" for reason, n in (report.get("failed_frames") or {}).items())
    lines = [f"{report['log']}: {report['frames']} frames" + (f", failed: {failed}" if failed else "")]
    bands = next(iter(methods.values())).keys() if methods else []
    for band in bands:
        lines += ["", "all ranges" if band == "all" else f"range {band} m", header]
        for name, scores in methods.items():
            lines.append(f"{name:<{width}} " + " ".join(f"{_cell(m, scores[band][m]):>8}" for m in METRICS))
    common = report.get("common_cells")
    if common and len(common) > 1:
        lines += ["", "elevation RMSE (m) on the cells every method covers"]
        lines.append(f"{'method':<{width}} " + " ".join(f"{band:>8}" for band in bands))
        for name, per_band in common.items():
            lines.append(f"{name:<{width}} "
                         + " ".join(f"{_cell('', per_band[b]['elevation_rmse_m']):>8}" for b in bands))
    return "\n".join(lines + _obstacle_lines(report.get("obstacles")))


def _obstacle_lines(obstacles: dict | None) -> list[str]:
    """Per true obstacle: frames from first eligible to first confirmed, track id switches and
    frames matched by more than one track."""
    if not obstacles or not obstacles.get("frames_to_confirmation"):
        return []
    confirm, switches = obstacles["frames_to_confirmation"], obstacles["id_switches"]
    duplicates = obstacles.get("duplicate_frames", {})
    width = max(len(key) for key in confirm)
    lines = ["", f"true obstacles ≥ {obstacles['min_height_m']} m within {obstacles['range_m']} m "
             "against terrainmap's confirmed tracks",
             f"{'obstacle':<{width}} {'frames to confirm':>18} {'id switches':>12} {'frames with 2+ tracks':>22}"]
    for key, frames in confirm.items():
        lines.append(f"{key:<{width}} {'never' if frames is None else frames:>18} {switches.get(key, '—'):>12} "
                     f"{duplicates.get(key, '—'):>22}")
    if (blocked := obstacles.get("blocked_by_cost")) is not None:
        lines.append(f"true obstacles within {obstacles['range_m']} m whose footprint holds a cell of cost 1, "
                     f"per frame: {100 * blocked:.1f} %")
    steep = obstacles.get("false_on_steep_ground_per_frame")
    if steep is not None:
        lines.append(f"false obstacles per frame within {obstacles['range_m']} m standing on ground steeper than "
                     f"cost.max_slope_deg: {steep:.2f}")
    return lines


def plot_rmse_vs_range(report: dict, path: str | Path) -> None:
    """Draw the elevation RMSE against range (2 m bins) for each method to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    edges = report["rmse_vs_range"]["range_edges_m"]
    step = edges[1] - edges[0]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, rmse in report["rmse_vs_range"]["methods"].items():
        points = [(edges[k] + step / 2, r) for k, r in enumerate(rmse) if r is not None]
        if points:
            ax.plot(*zip(*points), marker="o", label=name)
    ax.set_xlabel("range (m)")
    ax.set_ylabel("elevation RMSE (m)")
    ax.set_yscale("log")
    ax.set_title(f"{Path(report['log']).name}: {report['frames']} frames")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # no method with an RMSE: no legend (matplotlib would warn)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
