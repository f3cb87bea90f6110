"""surfstream in Python: optical-profiler height maps as numpy arrays.

Units: heights and lengths in micrometres (um); pitch as (x, y) um; arrays are
``rows x cols`` float64 with NaN where nothing was measured, row index growing with y.

The computations are the CLI's own Rust crates (readers, ISO 25178 parameters, ISO 16610
filters, wavelet separation, mesher), called in-process with the GIL released; graphs and
stitching run the ``surfstream`` CLI binary (see :func:`stitch`).

Copies (where arrays cross without one):

- ``read(path).heights`` is the reader's own buffer, handed to numpy (no copy).
- ``Surface(a).heights`` is ``a`` itself when ``a`` is a C-contiguous float64 array
  (``np.shares_memory(Surface(a).heights, a)``); any other array is converted once.
- ``params``, ``level``, the filters, ``separate``, ``mesh``, ``abbott``, ``psd`` borrow
  the heights read-only (no copy); their result arrays are the Rust results (no copy).
  The filters, ``separate`` and ``mesh`` work on a float32 copy about the mean, as the
  pipeline's frames do (DESIGN 2); ``write`` copies once into the writer.
"""

from __future__ import annotations

import html
import json
import os
import warnings
from base64 import b64encode
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native
from ._cli import RunResult, cli_binary, run, stitch
from ._errors import CliError, Error, FormatError, ParameterError, PathError, SurfstreamWarning

__all__ = [
    "Surface",
    "read",
    "stitch",
    "run",
    "RunResult",
    "cli_binary",
    "Error",
    "PathError",
    "FormatError",
    "ParameterError",
    "CliError",
    "SurfstreamWarning",
    "READABLE_EXTENSIONS",
    "WRITABLE_EXTENSIONS",
]

__version__: str = _native.__version__

#: Extensions :func:`read` takes (lower case, no dot), the CLI's readers.
READABLE_EXTENSIONS: Tuple[str, ...] = tuple(_native.readable_extensions())
#: Extensions :meth:`Surface.write` writes, the CLI's writers (``surfstream convert``).
WRITABLE_EXTENSIONS: Tuple[str, ...] = ("x3p", "npy")

PathLike = Union[str, "os.PathLike[str]"]
Pitch = Union[float, Tuple[float, float], Sequence[float]]


def _warn(messages: Sequence[str], stacklevel: int = 3) -> None:
    for m in messages:
        warnings.warn(m, SurfstreamWarning, stacklevel=stacklevel)


def _pitch(pitch_um: Pitch) -> Tuple[float, float]:
    if np.isscalar(pitch_um):
        x = y = float(pitch_um)  # type: ignore[arg-type]
    else:
        p = tuple(float(v) for v in pitch_um)  # type: ignore[union-attr]
        if len(p) != 2:
            raise ParameterError(f"pitch_um {pitch_um!r}: expected (x, y) in um or one number")
        x, y = p
    if not (np.isfinite(x) and x > 0 and np.isfinite(y) and y > 0):
        raise ParameterError(f"pitch_um ({x}, {y}): expected finite positive values in um")
    return (x, y)


class Surface:
    """A height map: ``heights`` (um, float64, rows x cols, NaN = not measured, rows grow
    with y), ``pitch_um`` = (x, y) um between columns and rows, ``metadata`` (a dict: what
    the file said, e.g. ``format``, ``instrument``, ``pitch_known``).

    ``Surface(a)`` keeps ``a`` itself when it is a C-contiguous float64 2-D array (no copy;
    the surfstream methods never write into it).
    """

    __slots__ = ("_heights", "_pitch_um", "_metadata")

    def __init__(
        self,
        heights: Any,
        pitch_um: Pitch = (1.0, 1.0),
        metadata: Optional[Mapping[str, Any]] = None,
    ) -> None:
        a = np.asarray(heights)
        if a.ndim != 2:
            raise ParameterError(f"heights: expected a 2-D array (rows x cols), got {a.ndim}-D")
        if a.shape[0] == 0 or a.shape[1] == 0:
            raise ParameterError(f"heights: empty map ({a.shape[0]} x {a.shape[1]}, rows x cols)")
        if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
            raise ParameterError(f"heights: expected real numbers (um), got dtype {a.dtype}")
        # No copy when the caller's array already is C-contiguous float64.
        self._heights = np.ascontiguousarray(a, dtype=np.float64)
        self._pitch_um = _pitch(pitch_um)
        self._metadata: Dict[str, Any] = dict(metadata) if metadata else {}

    # -- data -------------------------------------------------------------------------
    @property
    def heights(self) -> np.ndarray:
        """Heights in um, float64, rows x cols, NaN = not measured; row index grows with y."""
        return self._heights

    @property
    def pitch_um(self) -> Tuple[float, float]:
        """(x, y): spacing between columns and between rows, um."""
        return self._pitch_um

    @property
    def metadata(self) -> Dict[str, Any]:
        """What the file said (format, instrument, serial, date, pitch_known, extra, ...)."""
        return self._metadata

    @property
    def shape(self) -> Tuple[int, int]:
        """(rows, cols)."""
        return (int(self._heights.shape[0]), int(self._heights.shape[1]))

    @property
    def size_um(self) -> Tuple[float, float]:
        """(width x, height y) of the sampled area, um: (cols - 1) * pitch, (rows - 1) * pitch."""
        r, c = self.shape
        return ((c - 1) * self._pitch_um[0], (r - 1) * self._pitch_um[1])

    @property
    def invalid_count(self) -> int:
        """Points not measured (NaN)."""
        return int(np.isnan(self._heights).sum())

    def _args(self) -> Tuple[np.ndarray, float, float]:
        return (self._heights, self._pitch_um[0], self._pitch_um[1])

    def _like(self, heights: np.ndarray, **meta: Any) -> "Surface":
        m = dict(self._metadata)
        m.update(meta)
        return Surface(heights, self._pitch_um, m)

    # -- parameters -------------------------------------------------------------------
    def params(self, all: bool = False, pruning_pct: float = 5.0) -> Dict[str, float]:
        """ISO 25178-2 parameters, name -> value, the values and units of
        ``surfstream params --json`` (mean removed, nothing levelled: call :meth:`level` first
        for ``--level``). Heights um, Sdq dimensionless, Sdr %; with ``all=True`` also the
        spatial (Sal um, Str, Std deg), functional (Sk family um, Smr %, V* ml/m^2) and
        feature parameters (Wolf pruning at ``pruning_pct`` % of Sz). Undefined values NaN.
        """
        return {n: v for n, v, _, _ in _native.params(*self._args(), all, pruning_pct)}

    def params_table(self, all: bool = False, pruning_pct: float = 5.0) -> List[Tuple[str, float, str, str]]:
        """As :meth:`params`, as (name, value, unit, family) rows in the CLI's order."""
        return list(_native.params(*self._args(), all, pruning_pct))

    def abbott(self, samples: int = 256) -> Tuple[np.ndarray, np.ndarray]:
        """Abbott-Firestone curve: (material ratio %, height um about the mean)."""
        pts = np.asarray(_native.abbott(*self._args(), int(samples)), dtype=np.float64)
        return pts[:, 0], pts[:, 1]

    def psd(self) -> Tuple[np.ndarray, np.ndarray]:
        """Radially averaged power spectral density: (wavelength um, power um^4),
        longest wavelength first."""
        pts = np.asarray(_native.psd(*self._args()), dtype=np.float64).reshape(-1, 2)
        return pts[:, 0], pts[:, 1]

    # -- form and filters -------------------------------------------------------------
    def level(self) -> "Surface":
        """The heights minus their least-squares plane (``params --level``), um."""
        return self._like(_native.level(*self._args()))

    def remove_form(self, order: int = 1) -> "Surface":
        """The heights minus their least-squares polynomial of total ``order`` (1 = plane,
        2 = quadric, up to 10; ISO 25178-2 F-operator). The form's coefficients and residual
        RMS (um) are in the result's metadata under ``form``."""
        if int(order) < 0:
            raise ParameterError(f"order {order}: expected a polynomial order from 0 to 10")
        res, _form, coef, rms = _native.remove_form(*self._args(), int(order))
        return self._like(res, form={"order": int(order), "coefficients_um": coef, "residual_rms_um": rms})

    def form(self, order: int = 1) -> "Surface":
        """The least-squares polynomial form itself (see :meth:`remove_form`), um."""
        if int(order) < 0:
            raise ParameterError(f"order {order}: expected a polynomial order from 0 to 10")
        _res, form, _coef, _rms = _native.remove_form(*self._args(), int(order))
        return self._like(form)

    def gaussian(self, cutoff_um: float) -> "Surface":
        """ISO 16610-61 areal Gaussian filter: the mean (low-pass) surface for cutoff
        ``cutoff_um`` (lambda_c, um). ``self - mean`` is the roughness (see :meth:`separate`)."""
        return self._like(_native.gaussian(*self._args(), float(cutoff_um)))

    def robust_gaussian(self, cutoff_um: float, max_iterations: int = 30, tolerance: float = 1e-3) -> "Surface":
        """ISO 16610-71 robust Gaussian regression filter (zeroth order): the mean surface for
        cutoff ``cutoff_um`` (um), insensitive to deep valleys and spikes. Iterations and
        convergence are in the result's metadata under ``robust``."""
        mean, it, conv = _native.robust_gaussian(
            *self._args(), float(cutoff_um), int(max_iterations), float(tolerance)
        )
        return self._like(mean, robust={"iterations": it, "converged": conv})

    # -- pre-processing (surfstream prep) -----------------------------------------------
    def prep(self, *steps: Union[str, Tuple[str, str]]) -> "Surface":
        """The steps of ``surfstream prep``, in order, as ``"level plane"``, ``"filter l=80um"``
        or ``("crop", "x=0:100,y=0:50")``: a new Surface (pitch and NaN mask carried; a
        quarter turn swaps the pitch). What each step did (counts included) is in the result's
        metadata under ``prep``. The methods below are one step each."""
        pairs: List[Tuple[str, str]] = []
        for st in steps:
            if isinstance(st, str):
                name, _, arg = st.strip().lstrip("-").partition(" ")
                pairs.append((name, arg.strip()))
            else:
                name, arg = st
                pairs.append((str(name), str(arg)))
        h, px, py, done = _native.prep(*self._args(), pairs)
        m = dict(self._metadata)
        m["prep"] = list(m.get("prep", [])) + json.loads(done)
        return Surface(h, (px, py), m)

    def level_form(self, form: str = "plane") -> "Surface":
        """Removes a least-squares form: ``"plane"``, ``"poly=N"`` (N = 0..10), ``"sphere"``,
        ``"cylinder=x"`` or ``"cylinder=y"`` (``surfstream prep --level``)."""
        return self.prep(("level", form))

    def filter(self, l: Optional[Any] = None, s: Optional[Any] = None, robust: bool = False) -> "Surface":
        """ISO 16610 filtering (``prep --filter``): with ``l`` (lambda_c) the S-L surface,
        primary minus its Gaussian (``robust=True``: ISO 16610-71) L-filter mean; ``s``
        (lambda_s) alone, the primary surface. Lengths in um, or strings with a unit
        ("0.08mm")."""
        parts = ["robust" if robust else "gaussian"]
        if l is not None:
            parts.append(f"l={l}")
        if s is not None:
            parts.append(f"s={s}")
        return self.prep(("filter", ",".join(parts)))

    def crop(self, x: Tuple[Any, Any] = (0, None), y: Tuple[Any, Any] = (0, None)) -> "Surface":
        """Columns ``x = (start, end)`` and rows ``y`` (pixels, end not included; or lengths
        with a unit, "5um"); ``None`` = to the edge. Pitch kept."""
        def rng(r: Tuple[Any, Any], n: int) -> str:
            a, b = r
            return f"{0 if a is None else a}:{n if b is None else b}"
        rows, cols = self.shape
        return self.prep(("crop", f"x={rng(x, cols)},y={rng(y, rows)}"))

    def rotate(self, degrees: float) -> "Surface":
        """Counter-clockwise (x towards y): 90-degree steps exact, other angles bilinear on a
        square pitch (bounding box, corners not measured)."""
        return self.prep(("rotate", repr(float(degrees))))

    def fill(self, method: str = "laplace") -> "Surface":
        """The not-measured points filled: ``"laplace"`` (harmonic interpolation of the
        measured ones)."""
        return self.prep(("fill", method))

    def threshold(self, lower_pct: float = 0.5, upper_pct: Optional[float] = None) -> "Surface":
        """Drops the lowest ``lower_pct`` % and highest ``upper_pct`` % (default: the same) of
        the measured points (material ratio); they become NaN."""
        hi = lower_pct if upper_pct is None else upper_pct
        return self.prep(("threshold", f"{float(lower_pct)!r},{float(hi)!r}"))

    def remove_outliers(self, n_sigma: float = 3.0, method: str = "mean") -> "Surface":
        """Points farther than ``n_sigma`` standard deviations from the mean (``"mean"``: Sq)
        or the median (``"median"``: 1.4826 MAD) become NaN, one pass."""
        return self.prep(("outliers", f"{method},{float(n_sigma)!r}"))

    def separate(
        self,
        method: str = "wavelet",
        wavelet: str = "sym5",
        level: Union[int, str, None] = None,
        mode: str = "symmetric",
        cutoff_um: Optional[float] = None,
        lambda_s_um: Optional[float] = None,
    ) -> Tuple["Surface", "Surface"]:
        """Datum / roughness separation, ``surfstream separate``'s code: (datum, roughness),
        datum absolute in um, roughness = heights - datum in um.

        ``method="wavelet"``: the approximation of a 2-D DWT (PyWavelets semantics) at
        ``level`` (None: 8, or the deepest level that fits the map; an int, clamped to the
        largest useful level with a warning; or "auto": the minimum of the energy
        proportion), base ``wavelet`` (db1..db10, sym2..sym10,
        coif1..coif5 or "auto"), border ``mode`` ("symmetric" | "periodization").
        ``method="gaussian" | "robust-gaussian"``: the ISO 16610 L-filter with cutoff
        ``cutoff_um`` (um), optional S-filter ``lambda_s_um``. The choices made (level used,
        equivalent cutoff um, ...) are in each result's metadata under ``separation``.
        """
        d, r, summary, warns = _native.separate(
            *self._args(),
            method=str(method),
            wavelet=str(wavelet),
            level=None if level is None else str(level),
            mode=str(mode),
            cutoff_um=None if cutoff_um is None else float(cutoff_um),
            lambda_s_um=None if lambda_s_um is None else float(lambda_s_um),
        )
        _warn(warns)
        info = json.loads(summary)
        return self._like(d, separation=info), self._like(r, separation=info)

    # -- files ------------------------------------------------------------------------
    def write(self, path: PathLike) -> None:
        """Writes the map by the extension of ``path``: ``.x3p`` (ISO 25178-72, float64,
        NaN as invalid points, pitch kept) or ``.npy`` (float64 heights in um, NaN kept; .npy
        carries no pitch). Missing folders are created (as ``convert``)."""
        _native.write(os.fspath(path), *self._args())

    def mesh(
        self,
        path: PathLike,
        tolerance: Optional[str] = None,
        epsilon_um: Optional[float] = None,
        epsilon_sq: Optional[float] = None,
        level: bool = False,
        target: Optional[str] = None,
        grid: bool = False,
        max_triangles: Optional[int] = None,
        region_px: Optional[int] = None,
        model_method: str = "balanced",
        roughness: Optional["Surface"] = None,
        remove_spikes: bool = False,
        sheet: bool = False,
        holes: bool = False,
        ascii: bool = False,
        units: Optional[str] = None,
        base_depth_um: Optional[float] = None,
        curve: bool = True,
        **deprecated: Any,
    ) -> Dict[str, Any]:
        """Writes the map's triangle mesh as STL at ``path`` (it must end in ``.stl``):
        ``surfstream mesh`` with the same names and defaults, the same function (the mesher's
        one entry point) and the same record (the verb's ``OUT.json`` without ``input``).

        By default the fewest triangles that keep Sa, Sq, Sz, the residual and the largest
        pointwise error within the model's tolerance in every window (``tolerance``, the
        verb's ``--tolerance`` text, e.g. ``"sa=1,sq=1,sz=3,res=20,max=50"``; the target's
        own default without it). ``epsilon_um`` / ``epsilon_sq`` give a fixed vertical bound
        instead (um, or x Sq). ``level=True`` removes the least-squares plane first, as
        ``mesh --level`` and ``params(level=True)``. ``target`` = "liggghts" | "mercurydpm" |
        "edem" | "yade" sets format, kind, units and triangle budget (``grid=True``: the
        engine's regular grid); ``max_triangles`` bounds the search; ``roughness`` (a
        Surface on the same grid) makes the tolerance judge the roughness the mesh carries.
        Otherwise a closed solid (``sheet=True``: the open surface; ``holes=True`` keeps
        missing samples as holes), binary STL (``ascii=True``) in ``units`` "m" | "mm"
        (default) | "um". ``remove_spikes=True`` treats isolated spikes as not measured.
        ``curve=False`` (``mesh --no-curve``) makes only the tolerance search's own meshes:
        the record's fidelity-cost curve is then those, in less time.
        What the verb refuses is refused (``ParameterError``). The old ``tolerance_um`` /
        ``tolerance_sq`` still work, with a ``DeprecationWarning``."""
        for old, new in (("tolerance_um", "epsilon_um"), ("tolerance_sq", "epsilon_sq")):
            if old in deprecated:
                warnings.warn(
                    f"mesh({old}=...) is now {new}= (the verb's --{new.replace('_', '-')})",
                    DeprecationWarning,
                    stacklevel=2,
                )
                value = deprecated.pop(old)
                if new == "epsilon_um":
                    epsilon_um = value if epsilon_um is None else epsilon_um
                else:
                    epsilon_sq = value if epsilon_sq is None else epsilon_sq
        if deprecated:
            raise TypeError(f"mesh() got unexpected keyword arguments {sorted(deprecated)}")
        if roughness is not None and tuple(roughness.shape) != tuple(self.shape):
            raise ParameterError(
                f"roughness is {roughness.shape[0]} x {roughness.shape[1]} (rows x cols); the map is "
                f"{self.shape[0]} x {self.shape[1]}: expected the same grid"
            )
        out = _native.mesh(
            os.fspath(path),
            *self._args(),
            tolerance=None if tolerance is None else str(tolerance),
            epsilon_um=None if epsilon_um is None else float(epsilon_um),
            epsilon_sq=None if epsilon_sq is None else float(epsilon_sq),
            level=bool(level),
            target=None if target is None else str(target),
            grid=bool(grid),
            max_triangles=None if max_triangles is None else int(max_triangles),
            region_px=None if region_px is None else int(region_px),
            model_method=str(model_method),
            roughness_um=None if roughness is None else roughness._heights,
            remove_spikes=bool(remove_spikes),
            sheet=bool(sheet),
            holes=bool(holes),
            ascii=bool(ascii),
            units=None if units is None else str(units),
            base_depth_um=None if base_depth_um is None else float(base_depth_um),
            curve=bool(curve),
        )
        result: Dict[str, Any] = json.loads(out)
        return result

    # -- display ----------------------------------------------------------------------
    def preview_png(self, max_side_px: int = 256) -> Optional[bytes]:
        """A small PNG of the map (viridis over the 0.5-99.5 % heights, grey = not measured;
        the report's colour map), or None when nothing is measured."""
        p = _native.preview_png(self._heights, int(max_side_px))
        return None if p is None else bytes(p[0])

    def __repr__(self) -> str:
        r, c = self.shape
        fmt = self._metadata.get("format")
        return (
            f"<surfstream.Surface {r} x {c} (rows x cols), pitch {self._pitch_um[0]:.6g} x "
            f"{self._pitch_um[1]:.6g} um{', ' + str(fmt) if fmt else ''}>"
        )

    def _repr_html_(self) -> str:
        r, c = self.shape
        rows = [
            ("shape", f"{r} x {c} (rows x cols)"),
            ("pitch", f"{self._pitch_um[0]:.6g} x {self._pitch_um[1]:.6g} um (x, y)"),
            ("size", f"{self.size_um[0]:.6g} x {self.size_um[1]:.6g} um"),
        ]
        n_bad = self.invalid_count
        if n_bad:
            rows.append(("not measured", f"{n_bad} of {r * c} points"))
        img = ""
        if n_bad < r * c:
            p = self.params()
            # Heights as the CLI's verdict prints them: 3 significant figures, nm below 1 um.
            rows += [(k, _native.height_text(p[k])) for k in ("Sa", "Sq", "Sz")]
            png = _native.preview_png(self._heights, 256)
            if png is not None:
                data, lo, hi = png
                span = f"{_native.height_text(lo)} .. {_native.height_text(hi)}"
                # Drawn at the map's physical aspect (the pitch may differ along x and y).
                w_um, h_um = c * self._pitch_um[0], r * self._pitch_um[1]
                scale = 256.0 / max(w_um, h_um)
                w_px, h_px = max(1, round(w_um * scale)), max(1, round(h_um * scale))
                img = (
                    f'<img src="data:image/png;base64,{b64encode(bytes(data)).decode()}" '
                    f'style="image-rendering:pixelated;width:{w_px}px;height:{h_px}px" '
                    f'title="viridis {span}"/>'
                    f'<div style="font-size:smaller">{span}</div>'
                )
        fmt = self._metadata.get("format")
        if fmt:
            rows.append(("format", str(fmt)))
        table = "".join(
            f"<tr><th style='text-align:left'>{html.escape(k)}</th><td style='text-align:left'>{html.escape(v)}</td></tr>"
            for k, v in rows
        )
        return (
            "<div style='display:flex;gap:1em;align-items:flex-start'>"
            f"<div><b>surfstream.Surface</b><table>{table}</table></div><div>{img}</div></div>"
        )

    # -- plots (matplotlib only when called) --------------------------------------------
    def plot(self, ax: Any = None, cmap: str = "viridis", **kwargs: Any) -> Any:
        """The map with x / y in um and a colour bar in um (needs matplotlib)."""
        from ._plot import plot

        return plot(self, ax=ax, cmap=cmap, **kwargs)

    def plot_abbott(self, ax: Any = None, **kwargs: Any) -> Any:
        """The Abbott-Firestone curve (needs matplotlib)."""
        from ._plot import plot_abbott

        return plot_abbott(self, ax=ax, **kwargs)

    def plot_psd(self, ax: Any = None, **kwargs: Any) -> Any:
        """The radial PSD on log-log axes (needs matplotlib)."""
        from ._plot import plot_psd

        return plot_psd(self, ax=ax, **kwargs)


def read(path: PathLike, pitch_um: Optional[Pitch] = None) -> Surface:
    """Reads a height-map file (any format the CLI reads: .datx .dat .x3p .sur .plu .vk4
    .opd .zmg .nms .gsf .gwy .sdf .tmd .al3d .frt .mnt .di .spm .xyz/.txt/.csv/.asc .npy) into
    a Surface, heights in um. ``pitch_um`` is for files that carry no pitch (.npy); without it
    such files get 1 um with a warning, and giving it for a file that has one is an error (as
    the CLI).

    Raises PathError (missing path, or a folder), FormatError (unsupported extension or a
    file its reader refuses), with the CLI's message. Reader warnings become SurfstreamWarning.
    """
    p = os.fspath(path)
    heights, px, py, meta_json = _native.read(p)
    meta: Dict[str, Any] = json.loads(meta_json)
    _warn([f"{p}: {w}" for w in meta.get("warnings", [])])
    if pitch_um is not None:
        if meta.get("pitch_known"):
            raise ParameterError(
                f"{p}: the file carries its pitch ({px} x {py} um); pitch_um is only for files without one"
            )
        px, py = _pitch(pitch_um)
    elif not meta.get("pitch_known"):
        _warn([f"{p}: the file carries no pitch; assumed {px} x {py} um (give pitch_um)"])
    return Surface(heights, (px, py), meta)


def plot(surface: Surface, ax: Any = None, **kwargs: Any) -> Any:
    """:meth:`Surface.plot` as a function (needs matplotlib)."""
    return surface.plot(ax=ax, **kwargs)


def plot_abbott(surface: Surface, ax: Any = None, **kwargs: Any) -> Any:
    """:meth:`Surface.plot_abbott` as a function (needs matplotlib)."""
    return surface.plot_abbott(ax=ax, **kwargs)


def plot_psd(surface: Surface, ax: Any = None, **kwargs: Any) -> Any:
    """:meth:`Surface.plot_psd` as a function (needs matplotlib)."""
    return surface.plot_psd(ax=ax, **kwargs)


__all__ += ["plot", "plot_abbott", "plot_psd"]


def __dir__() -> List[str]:
    """The public names only: ``dir(surfstream)`` (and tab completion) shows the API, not the
    modules and typing names this one imports (np, os, json, Any, Dict, ...)."""
    return sorted(__all__ + ["__version__"])
