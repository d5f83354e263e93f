"""Plot helpers for the claims ledger: matplotlib with the Agg backend, atomic PNG writes."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless; must precede pyplot
import matplotlib.pyplot as plt  # noqa: E402

from ..run.results import write_atomic


def figure(ncols: int = 1, nrows: int = 1, width: float = 4.6, height: float = 3.6):
    """A figure with ``nrows × ncols`` axes (returned flat as a list)."""
    fig, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, height * nrows), squeeze=False,
                             layout="constrained")
    return fig, list(axes.ravel())


def save_png(fig, path: Path) -> None:
    """Save ``fig`` to ``path`` atomically and close it."""
    try:
        write_atomic(Path(path), lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    finally:
        plt.close(fig)


def message_png(path: Path, title: str, message: str) -> None:
    """A placeholder figure carrying a message (used when a check errored or drew nothing)."""
    import textwrap

    fig, (ax,) = figure(1, 1, 6.0, 2.5)
    ax.axis("off")
    ax.set_title(title)
    ax.text(0.0, 0.9, "\n".join(textwrap.wrap(message, 90)[:12]), va="top", ha="left", family="monospace", fontsize=7,
            transform=ax.transAxes)
    save_png(fig, path)


def loglog_fit(ax, x, y, label: str, *, fit=None, marker="o"):
    """Plot y(x) on log–log axes; with ``fit=(slope, intercept)`` (of log y on log x) draw the line."""
    import numpy as np

    line = ax.loglog(x, y, marker=marker, ls="-", label=label)[0]
    if fit is not None:
        s, c = fit
        xx = np.asarray(x, float)
        ax.loglog(xx, np.exp(c) * xx**s, ls=":", color=line.get_color(), label=f"fit slope {s:.2f}")
    return line
