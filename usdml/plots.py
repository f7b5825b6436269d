"""Charts of usdml's figures as PNG (matplotlib, which pyvista brings; the Agg backend: no display).

One function draws every chart (:func:`panels`): side-by-side axes, each with its title, labelled
axes (units in the labels) and named series; :func:`histogram` draws distributions. The tools in
``tools/`` and ``usdml compare --plot`` call them; the figures are the ones their tables print.
"""

from __future__ import annotations

from typing import Sequence

__all__ = ["error_map", "panels", "histogram", "series"]


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _axes(ax, title: str, xlabel: str, ylabel: str, legend: bool) -> None:
    """Title, labelled axes, a light grid and (for several series) a legend."""
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if legend:
        ax.legend(fontsize=8)


def _write(plt, fig, path: str) -> str:
    """``fig`` to ``path`` (:func:`_save`), then closed."""
    path = _save(fig, path)
    plt.close(fig)
    return path


#: dots per inch of every chart
DPI = 110


def _save(fig, path: str) -> str:
    from usdml.outputs import atomic_write

    # never a half-written picture; a folder that cannot be made is one line naming it
    atomic_write(path, ".png", lambda tmp: fig.savefig(tmp, dpi=DPI, bbox_inches="tight"))
    return path


def panels(path: str, charts: Sequence[dict], title: str | None = None) -> str:
    """Write side-by-side line charts to ``path``. Each chart: ``title``, ``xlabel``, ``ylabel`` (with units),
    ``series`` (``[(label, xs, ys)]``), optional ``logx`` / ``logy``."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(charts), figsize=(4.6 * len(charts), 3.6), squeeze=False)
    for ax, c in zip(axes[0], charts):
        for label, xs, ys in c["series"]:
            ax.plot(list(xs), list(ys), marker="o", label=str(label))
        if c.get("logx"):
            from matplotlib.ticker import FuncFormatter, NullFormatter
            ax.set_xscale("log")
            ticks = sorted({float(x) for _, xs, _ in c["series"] for x in xs})
            if len(ticks) <= 12:            # the measured values as the ticks, in plain numbers (1,000,000)
                ax.set_xticks(ticks)
                ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:,.0f}" if x >= 1 else f"{x:g}"))
                ax.xaxis.set_minor_formatter(NullFormatter())
        if c.get("logy"):
            ax.set_yscale("log")
        _axes(ax, c.get("title", ""), c["xlabel"], c["ylabel"], legend=len(c["series"]) > 1)
    if title:
        fig.suptitle(title)
    return _write(plt, fig, path)


def histogram(path: str, data: dict, xlabel: str, title: str | None = None, bins: int = 50) -> str:
    """Write histograms of each ``label -> values`` of ``data`` (overlaid, counts on a log axis) to ``path``."""
    import numpy as np
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    values = [np.asarray(v, float) for v in data.values()]
    lo = min((v.min() for v in values if v.size), default=0.0)
    hi = max((v.max() for v in values if v.size), default=1.0)
    edges = np.linspace(lo, hi if hi > lo else lo + 1e-9, bins + 1)
    for label, v in zip(data, values):
        ax.hist(v, bins=edges, histtype="step", linewidth=1.5, label=str(label))
    ax.set_yscale("log")
    _axes(ax, title or "", xlabel, "pixels", legend=True)
    return _write(plt, fig, path)


def error_map(path: str, rgb, scale: float, title: str) -> str:
    """An error heat map (``(H, W, 3)`` uint8, :func:`usdml.compare.error_heatmap`) drawn at least 6 inches
    (660 px) wide whatever its pixel count, square pixels, with a colour bar of the signed per-pixel
    error it encodes: red where the approximation is brighter (fewer lights blocked), blue darker,
    fully coloured from ``100 / scale`` %."""
    import numpy as np
    from matplotlib.colors import LinearSegmentedColormap, Normalize

    plt = _pyplot()
    h, w = rgb.shape[:2]
    width_in = 6.0
    fig, ax = plt.subplots(figsize=(width_in + 1.2, max(2.0, width_in * h / max(w, 1)) + 0.6))
    ax.imshow(np.asarray(rgb), interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title)
    full = 100.0 / scale
    cmap = LinearSegmentedColormap.from_list("error", [(1.0, 0.15, 0.1), (0.8, 0.8, 0.8), (0.1, 0.3, 1.0)])
    bar = fig.colorbar(plt.cm.ScalarMappable(Normalize(-full, full), cmap), ax=ax, fraction=0.046, pad=0.04)
    bar.set_label("signed error (wrongly hidden − visible) / lights, %")
    return _write(plt, fig, path)


def series(rows: Sequence[dict], x, y, group=None) -> list[tuple]:
    """Line series from table rows: ``x`` and ``y`` a key or a function of a row, ``group`` (a key or a
    function, None: one series) names the series; points sorted by x."""
    def get(f, r):
        return f(r) if callable(f) else r[f]
    out: dict = {}
    for r in rows:
        out.setdefault("" if group is None else get(group, r), []).append((get(x, r), get(y, r)))
    return [(label, [p[0] for p in sorted(pts)], [p[1] for p in sorted(pts)]) for label, pts in out.items()]
