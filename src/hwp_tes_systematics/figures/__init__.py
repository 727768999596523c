"""Figures (PNG) of each stage, one module per stage; all drawn with matplotlib's Agg backend."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt

from ..io import atomic_path

DPI = 120


def subplots(*args, **kwargs):
    """plt.subplots with constrained layout."""
    kwargs.setdefault("layout", "constrained")
    return plt.subplots(*args, **kwargs)


def save_figure(fig, path) -> None:
    """Save a figure as PNG atomically and close it."""
    with atomic_path(path) as temporary:
        fig.savefig(temporary, dpi=DPI, format="png")
    plt.close(fig)
