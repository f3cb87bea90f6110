"""Graphs and stitching: the ``surfstream`` CLI binary does them (``run``, ``stitch``), so the
Python package runs the same launcher, out-dir handling and verdict, not a second copy.

The binary is found as ``$SURFSTREAM_CLI``, else ``surfstream`` on PATH (``cargo install
--path launch`` from the repository puts it there; ``cargo build --release -p surfstream``
writes ``target/release/surfstream``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ._errors import CliError, ParameterError, SurfstreamWarning

PathLike = Union[str, "os.PathLike[str]"]


@dataclass
class RunResult:
    """What a graph run or a stitch left in its out dir.

    ``panorama``: the stitched height map (``panorama.npy``, absolute um, NaN = not
    measured) as a Surface with the run's pitch, or None when the graph made none;
    ``registrations``: run.json's tiles (each tile's final position and how it was placed)
    and pairs (each registration); ``run``: all of run.json; ``out``: the out dir;
    ``verdict``: the CLI's verdict text.
    """

    out: Path
    run: Dict[str, Any]
    panorama: Optional[Any] = None
    registrations: Dict[str, Any] = field(default_factory=dict)
    verdict: str = ""

    def __iter__(self):  # type: ignore[no-untyped-def]
        # `panorama, registrations = surfstream.stitch(...)`
        return iter((self.panorama, self.registrations))


def cli_binary() -> str:
    """The path of the ``surfstream`` CLI binary (``$SURFSTREAM_CLI`` or PATH)."""
    env = os.environ.get("SURFSTREAM_CLI")
    if env:
        if not (os.path.isfile(env) and os.access(env, os.X_OK)):
            raise CliError(f"SURFSTREAM_CLI={env}: not an executable file")
        return env
    found = shutil.which("surfstream")
    if found:
        return found
    raise CliError(
        "graphs and stitching run the surfstream CLI binary, and none was found: set "
        "SURFSTREAM_CLI to target/release/surfstream (cargo build --release -p surfstream) "
        "or put it on PATH (cargo install --path launch)"
    )


def _toml_value(v: Any) -> str:
    """A Python value as the TOML literal `--set NODE.PARAM=VALUE` reads."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ParameterError(f"set value {v!r}: expected a bool, number, string or list")


def _sets(set: Optional[Mapping[str, Any]]) -> List[str]:
    args: List[str] = []
    for k, v in (set or {}).items():
        if "." not in k:
            raise ParameterError(f"set {k!r}: expected NODE.PARAM (e.g. 'wavelet.level')")
        args += ["--set", f"{k}={_toml_value(v)}"]
    return args


def _call(args: List[str], out: Path) -> RunResult:
    proc = subprocess.run([cli_binary()] + args, capture_output=True, text=True)
    for line in proc.stderr.splitlines():
        if "warning:" in line:
            warnings.warn(line.strip(), SurfstreamWarning, stacklevel=3)
    if proc.returncode not in (0, 3):
        # The CLI's last words: `surfstream: error: MESSAGE`.
        errs = [l for l in proc.stderr.splitlines() if l.startswith("surfstream: error: ")]
        msg = errs[-1][len("surfstream: error: ") :] if errs else proc.stderr.strip()[-2000:]
        raise CliError(msg or f"surfstream {args[0]} exited with status {proc.returncode}")
    return _result(out, proc.stdout)


def _result(out: Path, verdict: str) -> RunResult:
    from . import Surface  # the package's class; imported here to avoid a cycle

    run_json = out / "run.json"
    run: Dict[str, Any] = json.loads(run_json.read_text()) if run_json.is_file() else {}
    panorama = None
    npy = out / "panorama.npy"
    if npy.is_file():
        pitch = _run_pitch(run)
        panorama = Surface(np.load(npy), pitch, {"format": "npy", "pitch_known": True, "file": str(npy)})
    regs = {k: run[k] for k in ("tiles", "pairs", "registration") if k in run}
    return RunResult(out=out, run=run, panorama=panorama, registrations=regs, verdict=verdict)


def _run_pitch(run: Mapping[str, Any]) -> Tuple[float, float]:
    """The panorama's pitch (um) from run.json."""
    for key in ("panorama", "scan", "outputs"):
        sec = run.get(key)
        if isinstance(sec, Mapping):
            for a, b in (("pitch_x_um", "pitch_y_um"),):
                if a in sec and b in sec:
                    return (float(sec[a]), float(sec[b]))
            if "pitch_um" in sec:
                p = sec["pitch_um"]
                if isinstance(p, (list, tuple)) and len(p) == 2:
                    return (float(p[0]), float(p[1]))
                return (float(p), float(p))
    raise CliError("run.json names no panorama pitch (scan.pitch_um)")


def run(graph: PathLike, out: PathLike, set: Optional[Mapping[str, Any]] = None, strict: bool = False) -> RunResult:
    """Runs a graph file (``surfstream run GRAPH -o OUT --set NODE.PARAM=VALUE``), nodes as
    threads in the CLI's process; ``set`` maps ``"node.param"`` to a value (TOML-converted).
    Returns the out dir's results (``RunResult``); raises CliError with the CLI's message."""
    out_p = Path(os.fspath(out))
    args = ["run", os.fspath(graph), "-o", str(out_p)] + _sets(set)
    if strict:
        args.append("--strict")
    return _call(args, out_p)


def _grid_arg(grid: Union[str, Tuple[int, int], Sequence[int]]) -> Tuple[int, int]:
    if isinstance(grid, str):
        parts = grid.lower().split("x")
        if len(parts) != 2:
            raise ParameterError(f"grid {grid!r}: expected ROWSxCOLS or (rows, cols)")
        r, c = int(parts[0]), int(parts[1])
    else:
        r, c = (int(v) for v in grid)
    if r < 1 or c < 1:
        raise ParameterError(f"grid {r} x {c}: expected at least 1 x 1")
    return r, c


def stitch(
    scan: Union[PathLike, Sequence[Any]],
    out: Optional[PathLike] = None,
    set: Optional[Mapping[str, Any]] = None,
    method: Optional[str] = None,
    grid: Optional[Union[str, Tuple[int, int]]] = None,
    overlap: Optional[float] = None,
    serpentine: bool = False,
    pitch_um: Optional[float] = None,
    height_unit: Optional[str] = None,
) -> RunResult:
    """Stitches a scan with the default pipeline (``surfstream stitch``): registration,
    fusion, wavelet separation, mesh; returns ``RunResult`` (``panorama, registrations =
    stitch(...)`` unpacks the panorama Surface and run.json's tiles and pairs).

    ``scan``: a scan directory (scan.toml), a scan.toml, a .mcap recording, or a folder of
    tiles (with ``grid``, or tiles that store their stage positions); or a sequence of tile
    files, Surfaces or 2-D arrays in acquisition order with ``grid=(rows, cols)`` and
    ``overlap`` (fraction of a field, e.g. 0.2); arrays need ``pitch_um``; they are written
    (files linked) into ``OUT.tiles/`` beside the out dir. ``height_unit``: the unit of the
    heights of arrays and of tile files that carry none (.npy, .xyz): "um", "nm", "mm" or "m"
    (``stitch --height-unit``; without it they are taken as um, with a warning). ``out``: the out dir (default: a
    new temporary folder). ``method``: auto | phase | harris | sift. ``set``: as for
    :func:`run`.
    """
    from . import Surface

    out_p = Path(os.fspath(out)) if out is not None else Path(tempfile.mkdtemp(prefix="surfstream-")) / "stitch"
    args: List[str] = ["stitch"]
    if isinstance(scan, (str, os.PathLike)):
        args.append(os.fspath(scan))
    else:
        if grid is None or overlap is None:
            raise ParameterError("stitch of files or arrays needs grid=(rows, cols) and overlap (e.g. 0.2)")
        tiles = list(scan)
        r, c = _grid_arg(grid)
        if len(tiles) != r * c:
            raise ParameterError(f"{len(tiles)} tiles for a {r} x {c} grid: expected {r * c}")
        # The tiles as files, beside the out dir (OUT.tiles/; the inferred OUT/scan.toml
        # names them), in acquisition order by name.
        folder = out_p.parent / (out_p.name + ".tiles")
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        for i, t in enumerate(tiles):
            name = f"tile_{i:04d}"
            if isinstance(t, (str, os.PathLike)):
                src = Path(os.fspath(t)).resolve()
                if not src.is_file():
                    raise ParameterError(f"{src}: no such file")
                os.symlink(src, folder / f"{name}{src.suffix.lower()}")
            elif isinstance(t, Surface):
                t.write(folder / f"{name}.x3p")  # X3P keeps the pitch
            else:
                if pitch_um is None:
                    raise ParameterError("tiles given as arrays carry no pitch: give pitch_um")
                np.save(folder / f"{name}.npy", np.ascontiguousarray(np.asarray(t, dtype=np.float64)))
        args.append(str(folder))
    if grid is not None:
        r, c = _grid_arg(grid)
        if overlap is None:
            raise ParameterError("grid needs overlap (a fraction of a field, e.g. 0.2)")
        args += ["--grid", f"{r}x{c}", "--overlap", repr(float(overlap))]
        if serpentine:
            args.append("--serpentine")
    if pitch_um is not None:
        args += ["--pitch-um", repr(float(pitch_um))]
    if height_unit is not None:
        args += ["--height-unit", str(height_unit)]
    if method is not None:
        args += ["--method", str(method)]
    args += ["-o", str(out_p)] + _sets(set)
    return _call(args, out_p)
