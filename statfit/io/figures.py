"""matplotlib figures as PNG bytes: pyplot on its file-only backend, imported when a figure is drawn,
so a command that draws none does not pay its ~0.4 s."""
from __future__ import annotations

import io

DPI = 80


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_png(figure) -> bytes:
    """``figure`` as PNG bytes at :data:`DPI`; the figure is closed."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    pyplot().close(figure)
    return buffer.getvalue()
