"""The Python package against the CLI (the same crates, so to 1e-9), against independent
references (the specimens' published values, numpy, PyWavelets, trimesh), and its promises:
round trips, NaN, exceptions with the CLI's messages, no copies where promised.

Paths: the repository is two folders up; the specimens are its tests/data/specimens (a folder
$SURFSTREAM_SPECIMENS names is looked in first); the CLI is $SURFSTREAM_CLI or
target/release/surfstream.
"""

import json
import math
import os
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

import surfstream as ss

REPO = Path(__file__).resolve().parents[2]
SPECIMENS = REPO / "tests" / "data" / "specimens"
SPECIMEN_DIRS = [Path(d) for d in [os.environ.get("SURFSTREAM_SPECIMENS")] if d] + [SPECIMENS]
CLI = Path(os.environ.get("SURFSTREAM_CLI", REPO / "target" / "release" / "surfstream"))


def specimen(name):
    """A real instrument file: $SURFSTREAM_SPECIMENS when it holds it, else the repository's."""
    return next((d / name for d in SPECIMEN_DIRS if (d / name).is_file()), SPECIMENS / name)


SPECIMEN_FILES = sorted(
    {
        p.name
        for d in SPECIMEN_DIRS
        if d.is_dir()
        for p in d.glob("*")
        if p.is_file() and p.suffix.lower().lstrip(".") in ss.READABLE_EXTENSIONS
    }
)

needs_specimens = pytest.mark.skipif(not SPECIMEN_FILES, reason=f"no specimens at {SPECIMENS}")
needs_cli = pytest.mark.skipif(not CLI.is_file(), reason=f"no CLI binary at {CLI} (cargo build --release)")


def cli(*args, check=True):
    p = subprocess.run([str(CLI), *map(str, args)], capture_output=True, text=True)
    if check and p.returncode != 0:
        raise AssertionError(f"surfstream {args}: {p.stderr}")
    return p


def cli_error(*args):
    p = cli(*args, check=False)
    assert p.returncode != 0, p.stdout
    lines = [l for l in p.stderr.splitlines() if l.startswith("surfstream: error: ")]
    assert lines, p.stderr
    return lines[-1][len("surfstream: error: "):]


def close(a, b, rel=1e-9):
    if a is None or b is None or (isinstance(a, float) and math.isnan(a)) or (isinstance(b, float) and math.isnan(b)):
        a = float("nan") if a is None else a
        b = float("nan") if b is None else b
        return math.isnan(a) and math.isnan(b)
    return math.isclose(a, b, rel_tol=rel, abs_tol=1e-12)


# -- parameters: every specimen, the CLI's numbers ---------------------------------------------


@needs_specimens
@needs_cli
@pytest.mark.parametrize("name", SPECIMEN_FILES)
@pytest.mark.parametrize("all_", [False, True])
def test_params_match_cli(name, all_):
    path = specimen(name)
    args = ["params", "--json", path] + (["--all"] if all_ else [])
    ref = json.loads(cli(*args).stdout)
    s = ss.read(path)
    got = s.params(all=all_)
    names = list(ref["units"])
    assert sorted(got) == sorted(names)
    for n in names:
        assert close(got[n], ref[n]), f"{name} {n}: python {got[n]!r} vs CLI {ref[n]!r}"
    # The same units, shape and pitch as the CLI reports.
    assert {n: u for n, _, u, _ in s.params_table(all=all_)} == ref["units"]
    assert s.shape == (ref["rows"], ref["cols"])
    assert s.pitch_um == (ref["pitch_x_um"], ref["pitch_y_um"])
    assert s.heights.size - s.invalid_count == ref["valid_points"]


@needs_cli
@needs_specimens
def test_level_matches_cli_level():
    path = specimen("x3p-2.x3p")
    ref = json.loads(cli("params", "--json", "--level", path).stdout)
    got = ss.read(path).level().params()
    for n in got:
        assert close(got[n], ref[n]), n


# Published values (tests/data/specimens/README.md: SurfaceTopography's test, surfalize 0.19.2):
# an independent check of the readers, not of our own numbers.
REFERENCE_SQ = {
    "metropro-1.dat": (0.07528822204734589, 50.10827568297134, 51.47133201226055),
    "x3p-2.x3p": (0.0772803327, -0.314420687, 0.239915513),
    "sur-2.sur": (0.017517881243588176, 8.9120001041465, 10.38800012139518),
    # Not in the repository (GPL-3, LGPL-3): checked where $SURFSTREAM_SPECIMENS holds them.
    "sur-uncompressed.sur": (0.119146667, -0.29729292, 0.329202298),
    "sample4_bin.x3p": (610537.577, -808000, 1048000),
}


@needs_specimens
@pytest.mark.parametrize("name", sorted(REFERENCE_SQ))
def test_read_matches_published_reference(name):
    if not specimen(name).is_file():
        pytest.skip(f"{name} not in {SPECIMEN_DIRS}")
    sq, lo, hi = REFERENCE_SQ[name]
    s = ss.read(specimen(name))
    h = s.heights[np.isfinite(s.heights)]
    assert math.isclose(s.params()["Sq"], sq, rel_tol=1e-7)
    assert math.isclose(float(np.sqrt(np.mean((h - h.mean()) ** 2))), sq, rel_tol=1e-7)
    # The height range (absolute z depends on the .sur offset convention, README there).
    assert math.isclose(float(h.max() - h.min()), hi - lo, rel_tol=1e-7)
    if not name.endswith(".sur"):
        assert math.isclose(float(h.min()), lo, rel_tol=1e-7)


def test_params_of_an_array_against_numpy():
    rng = np.random.default_rng(7)
    z = rng.normal(0.0, 0.3, (300, 200)) + np.linspace(0, 1, 200)[None, :]
    p = ss.Surface(z, pitch_um=(0.5, 0.7)).params()
    c = z - z.mean()
    assert math.isclose(p["Sa"], float(np.abs(c).mean()), rel_tol=1e-12)
    assert math.isclose(p["Sq"], float(np.sqrt((c**2).mean())), rel_tol=1e-12)
    assert math.isclose(p["Sz"], float(c.max() - c.min()), rel_tol=1e-12)
    assert math.isclose(p["Ssk"], float((c**3).mean() / (c**2).mean() ** 1.5), rel_tol=1e-10)
    dx = np.diff(z, axis=1) / 0.5
    dy = np.diff(z, axis=0) / 0.7
    assert math.isclose(p["Sdq"], float(np.sqrt((dx**2).mean() + (dy**2).mean())), rel_tol=1e-10)


# -- NaN --------------------------------------------------------------------------------------


def test_nan_points_are_left_out():
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 1.0, (128, 96))
    holes = rng.random(z.shape) < 0.1
    zn = np.where(holes, np.nan, z)
    s = ss.Surface(zn, 1.0)
    assert s.invalid_count == int(holes.sum())
    p = s.params()
    v = z[~holes]
    assert math.isclose(p["Sq"], float(np.sqrt(((v - v.mean()) ** 2).mean())), rel_tol=1e-12)
    assert math.isclose(p["Sa"], float(np.abs(v - v.mean()).mean()), rel_tol=1e-12)
    # Filters and separation keep NaN where nothing was measured.
    d, r = s.separate(level=2)
    assert np.array_equal(np.isnan(r.heights), holes)
    assert np.isnan(s.gaussian(20.0).heights[holes]).all()
    with pytest.raises(ss.Error, match="no valid"):
        ss.Surface(np.full((4, 4), np.nan)).params()


@needs_specimens
def test_specimen_invalid_points_are_nan():
    assert ss.read(specimen("sur-2.sur")).invalid_count == 117
    assert ss.read(specimen("sur-3.sur")).invalid_count == 233009
    if specimen("sample4_bin.x3p").is_file():
        s = ss.read(specimen("sample4_bin.x3p"))
        assert s.shape == (4, 4) and s.invalid_count == 1


# -- round trips --------------------------------------------------------------------------------


@needs_specimens
def test_round_trip_x3p_and_npy(tmp_path):
    s = ss.read(specimen("x3p-2.x3p"))
    s.write(tmp_path / "a.x3p")
    b = ss.read(tmp_path / "a.x3p")
    assert b.shape == s.shape and b.pitch_um == s.pitch_um
    # X3P stores metres: um -> m -> um may move the last bit.
    np.testing.assert_allclose(b.heights, s.heights, rtol=1e-15, atol=0)
    s.write(tmp_path / "a.npy")
    assert np.array_equal(np.load(tmp_path / "a.npy"), s.heights)
    # The pitch travels with the .npy, in its sidecar NAME.npy.json (as the CLI writes it).
    assert (tmp_path / "a.npy.json").is_file()
    c = ss.read(tmp_path / "a.npy")
    assert c.pitch_um == s.pitch_um and np.array_equal(c.heights, s.heights)
    # Without the sidecar the pitch is unknown: said, never guessed silently.
    (tmp_path / "a.npy.json").unlink()
    with pytest.warns(ss.SurfstreamWarning, match="carries no pitch"):
        c = ss.read(tmp_path / "a.npy")
    assert c.pitch_um == (1.0, 1.0)
    c = ss.read(tmp_path / "a.npy", pitch_um=s.pitch_um)
    assert np.array_equal(c.heights, s.heights) and c.pitch_um == s.pitch_um


def test_round_trip_keeps_nan(tmp_path):
    z = np.arange(35, dtype=np.float64).reshape(5, 7) * 0.01
    z[1, 2] = z[4, 6] = np.nan
    ss.Surface(z, (0.25, 0.5)).write(tmp_path / "n.x3p")
    b = ss.read(tmp_path / "n.x3p")
    assert b.pitch_um == (0.25, 0.5)
    assert np.array_equal(np.isnan(b.heights), np.isnan(z))
    np.testing.assert_allclose(b.heights, z, rtol=1e-15, atol=0)


@needs_cli
def test_written_x3p_reads_in_the_cli(tmp_path):
    z = np.random.default_rng(3).normal(size=(40, 50))
    s = ss.Surface(z, (0.8, 0.8))
    s.write(tmp_path / "c.x3p")
    ref = json.loads(cli("params", "--json", tmp_path / "c.x3p").stdout)
    assert close(s.params()["Sq"], ref["Sq"])


# -- exceptions: the right class, the CLI's message ----------------------------------------------


@needs_cli
def test_missing_path_raises_path_error_with_cli_message(tmp_path):
    missing = tmp_path / "nope.x3p"
    with pytest.raises(ss.PathError) as e:
        ss.read(missing)
    assert isinstance(e.value, FileNotFoundError) and isinstance(e.value, ss.Error)
    assert str(e.value) == cli_error("params", missing)


@needs_cli
def test_a_folder_raises_path_error_with_the_cli_message(tmp_path):
    with pytest.raises(ss.PathError) as e:
        ss.read(tmp_path)
    msg = str(e.value)
    assert msg.startswith(f"{tmp_path}: is a folder; read takes one height-map file (.npy"), msg
    assert "unsupported" not in msg
    # The CLI's verbs say the same, naming themselves.
    assert cli_error("inspect", tmp_path) == msg.replace("; read takes", "; inspect takes")


def test_the_namespace_is_the_api():
    names = dir(ss)
    for stray in ("Any", "Dict", "np", "os", "json", "html", "warnings", "b64encode"):
        assert stray not in names
    assert set(ss.__all__) <= set(names) and "read" in names and "Surface" in names
    assert all(hasattr(ss, n) for n in ss.__all__)


@needs_cli
def test_unsupported_format_raises_format_error_with_cli_message(tmp_path):
    f = tmp_path / "map.foo"
    f.write_bytes(b"\x00" * 64)
    with pytest.raises(ss.FormatError) as e:
        ss.read(f)
    assert "unsupported height-map format '.foo'" in str(e.value)
    assert str(e.value) == cli_error("params", f)
    bad = tmp_path / "bad.x3p"
    bad.write_bytes(b"not a zip file at all")
    with pytest.raises(ss.FormatError) as e:
        ss.read(bad)
    assert str(e.value) == cli_error("params", bad)
    with pytest.raises(ss.FormatError):
        ss.Surface(np.zeros((3, 3))).write(tmp_path / "x.png")
    # As `convert`: missing folders are created.
    ss.Surface(np.zeros((3, 3))).write(tmp_path / "new" / "folder" / "x.npy")
    assert (tmp_path / "new" / "folder" / "x.npy").is_file()


def test_bad_arguments_raise_parameter_error():
    s = ss.Surface(np.zeros((16, 16)))
    with pytest.raises(ss.ParameterError):
        ss.Surface(np.zeros((4, 4)), pitch_um=(0.0, 1.0))
    with pytest.raises(ss.ParameterError):
        ss.Surface(np.zeros(5))
    with pytest.raises(ss.ParameterError, match="wavelet"):
        s.separate(wavelet="nope")
    with pytest.raises(ss.ParameterError, match="cutoff"):
        s.separate(method="gaussian")
    with pytest.raises(ss.ParameterError):
        s.gaussian(-1.0)
    with pytest.raises(ValueError):  # ParameterError is a ValueError too
        s.mesh("x.stl", units="furlong")
    z = np.zeros((8, 8))
    z[2, 3] = np.inf
    with pytest.raises(ss.ParameterError, match="row 2"):
        ss.Surface(z).mesh("x.stl")


# -- no copies where promised ---------------------------------------------------------------------


def test_arrays_cross_without_copies():
    a = np.random.default_rng(0).normal(size=(64, 48))
    s = ss.Surface(a, 0.5)
    assert s.heights is a and np.shares_memory(s.heights, a)
    # Not C-contiguous float64: converted once, the caller's array untouched.
    t = ss.Surface(a.T)
    assert not np.shares_memory(t.heights, a) and np.array_equal(t.heights, a.T)
    f32 = ss.Surface(a.astype(np.float32))
    assert f32.heights.dtype == np.float64
    # Borrowed read-only: a read-only array works and is not written.
    ro = a.copy()
    ro.flags.writeable = False
    before = ro.copy()
    ss.Surface(ro).params(all=True)
    ss.Surface(ro).separate(level=2)
    assert np.array_equal(ro, before)
    # Results are the Rust buffers, owned through their base object (not numpy allocations).
    lv = s.level().heights
    assert lv.dtype == np.float64 and lv.flags.c_contiguous and not lv.flags.owndata
    assert not np.shares_memory(lv, a)


@needs_specimens
def test_read_hands_over_the_reader_buffer():
    h = ss.read(specimen("x3p-2.x3p")).heights
    assert h.dtype == np.float64 and h.flags.c_contiguous
    assert not h.flags.owndata and h.base is not None


# -- filters, separation, mesh ----------------------------------------------------------------------


@needs_cli
@needs_specimens
@pytest.mark.parametrize("method", ["wavelet", "gaussian", "robust-gaussian"])
def test_separate_matches_cli(tmp_path, method):
    path = specimen("x3p-2.x3p")
    extra = [] if method == "wavelet" else ["--cutoff-um", "25"]
    cli("separate", path, "--method", method, *extra, "-o", tmp_path)
    s = ss.read(path)
    kw = {} if method == "wavelet" else {"cutoff_um": 25.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ss.SurfstreamWarning)
        d, r = s.separate(method=method, **kw)
    datum = np.load(tmp_path / "datum.npy")
    rough = np.load(tmp_path / "roughness.npy")
    assert np.array_equal(d.heights, datum, equal_nan=True)
    assert np.array_equal(r.heights, rough.astype(np.float64), equal_nan=True)


def test_wavelet_datum_against_pywavelets():
    pywt = pytest.importorskip("pywt")
    rng = np.random.default_rng(5)
    z = np.cumsum(rng.normal(size=(200, 160)), axis=1) * 0.01 + rng.normal(size=(200, 160)) * 0.02
    s = ss.Surface(z, 1.0)
    d, r = s.separate(wavelet="sym5", level=3, mode="symmetric")
    m = z.mean()
    c = pywt.wavedec2(z - m, "sym5", mode="symmetric", level=3)
    c = [c[0]] + [tuple(np.zeros_like(x) for x in lvl) for lvl in c[1:]]
    ref = pywt.waverec2(c, "sym5", mode="symmetric")[:200, :160] + m
    # The separation takes f32 heights about the mean (as frames carry them).
    assert np.max(np.abs(d.heights - ref)) < 1e-5
    assert np.max(np.abs(d.heights + r.heights - z)) < 1e-5
    assert d.metadata["separation"]["level"] == 3


def test_level_lowered_warns():
    s = ss.Surface(np.random.default_rng(2).normal(size=(64, 64)), 1.0)
    with pytest.warns(ss.SurfstreamWarning):
        explicit, _ = s.separate(level=8)
    # The default (8, or the deepest level that fits) is lowered silently, to the same level.
    with warnings.catch_warnings():
        warnings.simplefilter("error", ss.SurfstreamWarning)
        default, _ = s.separate()
    assert default.metadata["separation"]["level"] == explicit.metadata["separation"]["level"] < 8


def test_filters_and_form():
    y, x = np.mgrid[0:120, 0:150].astype(np.float64)
    plane = 0.01 * x - 0.02 * y + 3.0
    wave = 0.5 * np.sin(2 * np.pi * x / 60.0)
    s = ss.Surface(plane + wave, 1.0)
    lev = s.level()
    # Removing the plane leaves the wave (whose own plane fit is small).
    assert np.max(np.abs(lev.heights - (wave - wave.mean()))) < 0.05
    r2 = s.remove_form(2)
    assert r2.metadata["form"]["order"] == 2 and len(r2.metadata["form"]["coefficients_um"]) == 6
    assert np.allclose(s.remove_form(1).heights + s.form(1).heights, s.heights, atol=1e-5)
    # A 25 um Gaussian mean line keeps a 300 um wave (transmission > 99 %) and removes a
    # 6 um one (transmission exp(-pi a^2 (25/6)^2) ~ 0).
    long = 0.5 * np.sin(2 * np.pi * x / 300.0)
    short = 0.2 * np.sin(2 * np.pi * x / 6.0)
    g = ss.Surface(long + short, 1.0).gaussian(25.0)
    inner = (slice(None), slice(30, 120))
    assert np.max(np.abs(g.heights[inner] - long[inner])) < 0.01
    rg = ss.Surface(wave + 1.0, 1.0).robust_gaussian(800.0)
    assert rg.metadata["robust"]["iterations"] >= 0


def test_mesh_writes_a_watertight_stl(tmp_path):
    z = np.random.default_rng(4).normal(size=(80, 90)) * 0.2
    stats = ss.Surface(z, 2.0).mesh(tmp_path / "s.stl", epsilon_um=0.05, units="um")
    assert (tmp_path / "s.stl").stat().st_size > 84
    assert stats["watertight"] is True and stats["triangles"] > 0
    assert stats["fidelity"]["error"]["max_um"] <= 0.05 + 1e-9
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.load(tmp_path / "s.stl")
    assert m.is_watertight and len(m.faces) == stats["triangles"]
    # x extent: (cols - 1) * pitch in um.
    assert math.isclose(float(m.extents[0]), 89 * 2.0, rel_tol=1e-6)


def test_mesh_takes_the_verbs_names_and_refuses_what_it_refuses(tmp_path):
    z = np.random.default_rng(5).normal(size=(64, 64)) * 0.2
    s = ss.Surface(z, 1.0)
    # The default is the verb's: the tolerance search, not a fixed bound.
    stats = s.mesh(tmp_path / "d.stl")
    assert stats["tolerance"]["tolerance"]["max_error_pct"] == 50.0
    # The old names still work, with a warning, and mean the fixed bound.
    with pytest.warns(DeprecationWarning, match="epsilon_um"):
        old = s.mesh(tmp_path / "o.stl", tolerance_um=0.05)
    assert "tolerance" not in old and old["fidelity"]["epsilon_um"] == 0.05
    for kw, says in [
        ({"units": "furlong"}, "units"),
        ({"model_method": "fast"}, "model_method"),
        ({"target": "ansys"}, "target"),
        ({"holes": True}, "sheet=True"),
        ({"tolerance": "sa=1", "epsilon_um": 0.1}, "not both"),
        ({"target": "yade", "units": "mm"}, "target sets"),
        ({"grid": True}, "needs a target"),
        ({"region_px": 4}, "region_px"),
    ]:
        with pytest.raises(ss.ParameterError, match=says):
            s.mesh(tmp_path / "x.stl", **kw)
    # An STL named otherwise is refused, naming the path, and nothing written.
    with pytest.raises(ss.ParameterError, match=r"x\.obj: mesh writes STL; expected a path ending in \.stl"):
        s.mesh(tmp_path / "x.obj")
    assert not (tmp_path / "x.obj").exists()


@needs_cli
@needs_specimens
@pytest.mark.parametrize(
    "py_kw, cli_args",
    [
        ({}, []),
        ({"level": True}, ["--level"]),
        ({"epsilon_sq": 0.05, "sheet": True, "units": "um"}, ["--epsilon-sq", "0.05", "--sheet", "--units", "um"]),
        ({"tolerance": "sa=1,sq=1,sz=3", "remove_spikes": True}, ["--tolerance", "sa=1,sq=1,sz=3", "--remove-spikes"]),
        ({"target": "yade"}, ["--target", "yade"]),
        ({"curve": False}, ["--no-curve"]),
    ],
)
def test_mesh_is_the_verbs(tmp_path, py_kw, cli_args):
    """Python's mesh and `surfstream mesh` are one function: the same STL bytes and the same
    record (the verb's OUT.json adds the input file and its format; mesh_s is a time)."""
    path = specimen("x3p-2.x3p")
    cli("mesh", path, *cli_args, "-o", tmp_path / "cli" / "m.stl")
    stats = ss.read(path).mesh(tmp_path / "py" / "m.stl", **py_kw)
    assert (tmp_path / "py" / "m.stl").read_bytes() == (tmp_path / "cli" / "m.stl").read_bytes()
    want = json.loads((tmp_path / "cli" / "m.json").read_text())
    for d in (want, stats):
        d.pop("mesh_s")
    assert want.pop("input") == str(path) and want.pop("input_format")
    assert want.pop("file") == "m.stl" and stats.pop("file") == str(tmp_path / "py" / "m.stl")
    assert stats == want
    if py_kw.get("level"):
        assert stats["form_removed"] == "least-squares plane"
    else:
        assert "form_removed" not in stats
    assert sorted(p.name for p in (tmp_path / "py").iterdir()) == ["m.stl"]


@needs_cli
@needs_specimens
def test_separate_summary_is_the_verbs(tmp_path):
    path = specimen("x3p-2.x3p")
    cli("separate", path, "--level", "3", "-o", tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ss.SurfstreamWarning)
        d, _ = ss.read(path).separate(level=3)
    want = json.loads((tmp_path / "separate.json").read_text())
    got = d.metadata["separation"]
    assert got == {k: want[k] for k in got}
    assert {"energy_curve", "equivalent_cutoff_um", "pooling_bias", "z_offset_um"} <= set(got)


# -- notebook --------------------------------------------------------------------------------------


def test_repr_html_has_shape_pitch_parameters_and_image():
    s = ss.Surface(np.random.default_rng(9).normal(size=(30, 40)), (0.5, 0.25))
    h = s._repr_html_()
    p = s.params()
    assert "30 x 40 (rows x cols)" in h and "0.5 x 0.25 um" in h
    for k in ("Sa", "Sq", "Sz"):
        assert f">{k}</th><td style='text-align:left'>{ss._native.height_text(p[k])}</td>" in h
    # Heights below 1 um in nm, 3 significant figures (a MetroPro 3 x 3 read "0.005 um"):
    # +-5.12 nm in a checkerboard has Sa = Sq = 5.12 nm, Sz = 10.24 nm.
    z = np.where(np.indices((6, 6)).sum(axis=0) % 2 == 0, 0.00512, -0.00512)
    h = ss.Surface(z, 1.0)._repr_html_()
    for k, text in (("Sa", "5.12 nm"), ("Sq", "5.12 nm"), ("Sz", "10.2 nm")):
        assert f">{k}</th><td style='text-align:left'>{text}</td>" in h, h
    assert "data:image/png;base64," in h
    png = s.preview_png()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_helpers_without_requiring_matplotlib():
    s = ss.Surface(np.random.default_rng(9).normal(size=(30, 40)), 1.0)
    mr, z = s.abbott(64)
    assert mr[0] <= mr[-1] and z[0] >= z[-1]
    wl, pw = s.psd()
    assert len(wl) == len(pw) > 0
    mpl = pytest.importorskip("matplotlib")
    mpl.use("Agg")
    s.plot()
    ss.plot_abbott(s)
    ss.plot_psd(s)


# -- graphs and stitching (the CLI binary) ---------------------------------------------------------


@needs_cli
def test_stitch_arrays_with_a_grid(tmp_path, monkeypatch):
    monkeypatch.setenv("SURFSTREAM_CLI", str(CLI))
    rng = np.random.default_rng(11)
    # A rough, isotropic specimen: smoothed noise, 0.5 um pitch.
    f = np.fft.rfft2(rng.normal(size=(420, 420)))
    ky = np.fft.fftfreq(420)[:, None]
    kx = np.fft.rfftfreq(420)[None, :]
    spec = np.fft.irfft2(f / (1.0 + (np.hypot(kx, ky) * 60) ** 2), s=(420, 420))
    spec = spec / spec.std()
    tile, step = 240, 180  # 25 % overlap
    tiles = [spec[r * step : r * step + tile, c * step : c * step + tile] for r in range(2) for c in range(2)]
    # Arrays carry no unit: without height_unit they are taken as um, said.
    with pytest.warns(ss.SurfstreamWarning, match="heights taken as um"):
        ss.stitch(tiles, out=tmp_path / "assumed", grid=(2, 2), overlap=0.25, pitch_um=0.5)
    # Stated (here in nm): no warning, and the panorama is in um.
    with warnings.catch_warnings():
        warnings.simplefilter("error", ss.SurfstreamWarning)
        nm = [t * 1000.0 for t in tiles]
        res = ss.stitch(nm, out=tmp_path / "out", grid=(2, 2), overlap=0.25, pitch_um=0.5, height_unit="nm")
    pano, regs = res
    assert isinstance(pano, ss.Surface)
    assert pano.pitch_um == (0.5, 0.5)
    rows, cols = pano.shape
    assert abs(rows - 420) <= 4 and abs(cols - 420) <= 4
    assert regs and (tmp_path / "out" / "run.json").is_file()
    # The panorama is the specimen (up to a piston): compare the common part.
    r0, c0 = min(rows, 420), min(cols, 420)
    diff = pano.heights[:r0, :c0] - spec[:r0, :c0]
    diff = diff[np.isfinite(diff)]
    assert np.std(diff) < 0.05 * spec.std()


@needs_cli
def test_run_reports_the_cli_error(tmp_path, monkeypatch):
    monkeypatch.setenv("SURFSTREAM_CLI", str(CLI))
    graph = REPO / "launch" / "graphs" / "demo.toml"
    with pytest.raises(ss.CliError) as e:
        ss.run(graph, tmp_path / "o", set={"wavelet.no_such_param": 1})
    assert "no_such_param" in str(e.value)
    assert str(e.value) == cli_error("run", graph, "-o", tmp_path / "o2", "--set", "wavelet.no_such_param=1")


def test_cli_missing_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setenv("SURFSTREAM_CLI", str(tmp_path / "absent"))
    with pytest.raises(ss.CliError, match="SURFSTREAM_CLI"):
        ss.run("g.toml", tmp_path / "o")


# -- the documentation's example runs as written ---------------------------------------------------


@needs_specimens
def test_docs_example_runs(tmp_path, monkeypatch):
    doc = (REPO / "docs" / "python.md").read_text()
    code = doc.split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    code = code.replace('"measurement.x3p"', repr(str(specimen("x3p-2.x3p"))))
    exec(compile(code, "docs/python.md", "exec"), {})
    assert (tmp_path / "datum.stl").stat().st_size > 84
    assert ss.read(tmp_path / "datum.x3p").shape == (650, 650)


def test_the_gil_is_released_during_computation():
    # The main thread counts while a worker computes: with the GIL held for the whole call
    # the count could not move between the worker's two reads of it.
    import threading

    s = ss.Surface(np.random.default_rng(6).normal(size=(1024, 1024)), 1.0)
    state = {"count": 0, "during": None}

    def worker():
        before = state["count"]
        s.params(all=True)
        state["during"] = state["count"] - before

    t = threading.Thread(target=worker)
    t.start()
    while t.is_alive():
        state["count"] += 1
    t.join()
    assert state["during"] > 100, state


@needs_cli
def test_run_a_graph_with_overrides(tmp_path, monkeypatch):
    monkeypatch.setenv("SURFSTREAM_CLI", str(CLI))
    sets = {"stage.tile_px": 256, "stage.pacing": "fast", "stage.rows": 1, "stage.cols": 2, "wavelet.level": 3}
    r = ss.run(REPO / "launch" / "graphs" / "demo.toml", tmp_path / "demo", set=sets)
    assert r.out == tmp_path / "demo" and "surfstream: done" in r.verdict
    assert r.run["parameters"]["wavelet"]["level"] == 3
    assert len(r.registrations["tiles"]) == 2
    pano = r.panorama
    assert pano.pitch_um == (0.8148, 0.8148) and pano.shape[0] >= 256
    ref = json.loads(cli("params", "--json", "--pitch-um", 0.8148, tmp_path / "demo" / "panorama.npy").stdout)
    got = pano.params()
    for n in ("Sa", "Sq", "Sz", "Sdr"):
        assert close(got[n], ref[n]), n


# -- pre-processing (surfstream prep) ----------------------------------------------------------


def test_prep_methods_return_new_surfaces_keeping_pitch_and_nan():
    y, x = np.mgrid[0:40, 0:60]
    z = 3.0 + 0.02 * x - 0.05 * y + 1e-3 * x * y
    s = ss.Surface(z, pitch_um=(0.5, 0.25))
    lv = s.level_form("poly=2")
    assert lv is not s and lv.pitch_um == s.pitch_um
    assert np.nanmax(np.abs(lv.heights)) < 1e-6
    c = s.crop(x=(10, 30), y=(5, None))
    assert c.shape == (35, 20) and c.pitch_um == (0.5, 0.25)
    assert np.array_equal(c.heights, z[5:, 10:30])
    r = s.rotate(90)
    assert r.shape == (60, 40) and r.pitch_um == (0.25, 0.5)
    holed = z.copy()
    holed[10:20, 20:35] = np.nan
    f = ss.Surface(holed, 1.0).fill()
    assert not np.isnan(f.heights).any()
    # A harmonic interpolation keeps a plane; this one has a small x*y term (also harmonic).
    assert np.abs(f.heights - z).max() < 1e-6
    assert f.metadata["prep"][0]["points_filled"] == 150
    t = ss.Surface(z, 1.0).threshold(1.0, 1.0)
    assert t.invalid_count == t.metadata["prep"][0]["points_removed"] > 0
    hp = s.filter(l=5.0)
    assert abs(float(np.nanmean(hp.heights))) < 1e-3
    chained = s.prep("level plane", ("crop", "x=0:30,y=0:20"))
    assert chained.shape == (20, 30) and len(chained.metadata["prep"]) == 2
    with pytest.raises(ss.ParameterError, match="expected plane"):
        s.level_form("cone")


@needs_specimens
def test_prep_level_matches_surfalize():
    surfalize = pytest.importorskip("surfalize")
    path = specimen("x3p-2.x3p")
    ours = ss.read(path).level_form("plane").heights
    ref = surfalize.Surface.load(str(path)).level().data
    assert np.abs(ours - ref).max() < 2e-5
