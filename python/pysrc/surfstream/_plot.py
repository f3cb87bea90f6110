"""Optional matplotlib helpers: imported only when a plot is asked for, so matplotlib is not
a requirement of the package (``pip install ./python[plot]`` adds it)."""

from __future__ import annotations

from typing import Any


def _pyplot() -> Any:
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("surfstream's plot helpers need matplotlib: pip install matplotlib") from e
    return plt


def _axes(ax: Any) -> Any:
    if ax is not None:
        return ax
    return _pyplot().subplots()[1]


def plot(surface: Any, ax: Any = None, cmap: str = "viridis", **kwargs: Any) -> Any:
    """The height map, x and y in um (row 0 at the top, as the preview PNGs), colour bar in um;
    the colour range is the 0.5-99.5 % heights unless vmin / vmax are given."""
    import numpy as np

    ax = _axes(ax)
    h = surface.heights
    px, py = surface.pitch_um
    rows, cols = surface.shape
    finite = h[np.isfinite(h)]
    if finite.size and "vmin" not in kwargs and "vmax" not in kwargs:
        lo, hi = np.percentile(finite, [0.5, 99.5])
        kwargs.update(vmin=lo, vmax=hi)
    im = ax.imshow(h, cmap=cmap, extent=(0, cols * px, rows * py, 0), interpolation="nearest", **kwargs)
    ax.set_xlabel("x (um)")
    ax.set_ylabel("y (um)")
    ax.figure.colorbar(im, ax=ax, label="height (um)")
    return ax


def plot_abbott(surface: Any, ax: Any = None, samples: int = 256, **kwargs: Any) -> Any:
    """The Abbott-Firestone (material ratio) curve: height um about the mean vs material ratio %."""
    ax = _axes(ax)
    mr, z = surface.abbott(samples)
    ax.plot(mr, z, **kwargs)
    ax.set_xlabel("material ratio (%)")
    ax.set_ylabel("height (um)")
    ax.set_xlim(0, 100)
    return ax


def plot_psd(surface: Any, ax: Any = None, **kwargs: Any) -> Any:
    """The radially averaged PSD, power um^4 vs wavelength um, log-log."""
    ax = _axes(ax)
    wl, p = surface.psd()
    ax.loglog(wl, p, **kwargs)
    ax.set_xlabel("wavelength (um)")
    ax.set_ylabel("PSD (um^4)")
    ax.invert_xaxis()
    return ax
