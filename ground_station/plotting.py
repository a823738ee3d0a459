"""The ground station's matplotlib entry: headless pyplot and figure -> PNG bytes.

matplotlib is imported only when a plot is made (it is slow to import and
most commands draw nothing), always on the Agg backend so plotting works
without a display. Callers write the bytes with `firmware_py.atomic`.
"""

from __future__ import annotations

import io


def pyplot():
    """matplotlib.pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def png_bytes(fig, **savefig_kwargs) -> bytes:
    """Render `fig` as PNG bytes and close it (savefig_kwargs: dpi, bbox_inches, ...)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig_kwargs)
    pyplot().close(fig)
    return buf.getvalue()
