#!/usr/bin/env python3
"""Reading 1024^2 instrument files: makes the inputs once, then times our readers on them.

    .bench-venv/bin/python scripts/bench_params_read.py [--out bench-out/read] [--reps 15]

Inputs (all from the same synthetic 1024^2 surface, benchkit.synth_surface, um, pitch 0.5 um):
  s1024.npy          float64
  s1024.x3p          our x3p writer (`surfstream convert`: float64; data.bin stored, since
                     measured f64 heights barely deflate)
  s1024_deflated.x3p the same archive re-packed with every entry deflated (Python zipfile,
                     level 6), as other writers make them
  s1024_f32.datx     DATX layout of ../shared/bench/make_synthetic_datx.py, float32, contiguous
  s1024_f64gz.datx   the same, float64, gzip-chunked (64 rows per chunk)
  s1024.sur          Digital Surf, int32 1 nm steps, plain
  s1024c.sur         the same, DSCOMPRESSED (zlib streams)
The .sur files come from `metrology_bench make-sur` (the benchmark's writer). Needs h5py (the
bench venv), `cargo build --release -p surfstream` and `cargo build --release -p
surfstream-common --example metrology_bench` (CARGO_TARGET_DIR honoured). Prints the reader's JSON lines (median, min, max
seconds over the repeats, first read not counted) and the process CPU seconds per read, and
beside each, in the same run, the anchor reading the same file in this Python: surfalize's
`Surface.load` (x3p, sur; it has no .datx reader) or h5py (libhdf5) reading the .datx height
dataset and converting it to um with NaN for No Data; "ratio" = anchor median / ours.
"""
import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
import zipfile

import h5py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "..", "shared", "bench"))
from benchkit import synth_surface  # noqa: E402


def write_datx(path, z_um, dtype, gzip):
    s = 'S64'
    surface_path = '/Data/Surface/{00000000-0000-0000-0000-000000000001}'
    with h5py.File(path, 'w') as h5:
        md = np.array([(b'Root', b'Measurement', b'{M}'), (b'{M}', b'Surface', b'{S}'),
                       (b'{S}', b'Path', surface_path.encode())],
                      dtype=[('Source', s), ('Link', s), ('Destination', s)])
        h5.create_dataset('MetaData', data=md)
        kw = dict(chunks=(64, z_um.shape[1]), compression='gzip') if gzip else {}
        ds = h5.create_dataset(surface_path, data=(z_um * 1e3).astype(dtype), **kw)  # nm
        cdt = np.dtype([('Category', s), ('BaseUnit', s), ('Parameters', h5py.vlen_dtype(np.float64))])

        def conv(cat, unit, p):
            c = np.empty(1, dtype=cdt)
            c[0] = (cat.encode(), unit.encode(), np.array(p, 'f8'))
            return c
        ds.attrs['X Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
        ds.attrs['Y Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
        ds.attrs['Z Converter'] = conv('HeightCat', 'NanoMeters', [0, 6.33e-7, 0.5, 1.0])
        ds.attrs['Unit'] = np.array([b'NanoMeters'], dtype=s)
        ds.attrs['No Data'] = np.array([np.finfo(dtype).max], dtype)


def anchor_read(path):
    """(tool, seconds) of the anchor's read of `path` into a float64 um array."""
    if path.endswith(".datx"):
        with h5py.File(path, "r") as h5:
            ds = h5["/Data/Surface/{00000000-0000-0000-0000-000000000001}"]
            z = ds[()].astype(np.float64)
            no_data = ds.attrs["No Data"][0]
            z[z >= no_data] = np.nan
            z *= 1e-3
        return "h5py", z
    from surfalize import Surface
    return "surfalize", Surface.load(path).data


def time_anchor(path, reps):
    times = []
    for _ in range(reps + 1):
        t = time.perf_counter()
        tool, z = anchor_read(path)
        times.append(time.perf_counter() - t)
    assert z.shape == (1024, 1024), z.shape
    return tool, statistics.median(times[1:])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench-out/read")
    ap.add_argument("--reps", type=int, default=15)
    a = ap.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target"))
    bench = os.path.join(target, "release", "examples", "metrology_bench")
    cli = os.path.join(target, "release", "surfstream")
    for b in (bench, cli):
        if not os.path.exists(b):
            sys.exit(f"{b} missing: cargo build --release -p surfstream; "
                     "cargo build --release -p surfstream-io --example metrology_bench")
    os.makedirs(a.out, exist_ok=True)
    p = lambda name: os.path.join(a.out, name)  # noqa: E731
    if not os.path.exists(p("s1024.npy")):
        np.save(p("s1024.npy"), synth_surface(1024, seed=1024))
    z = np.load(p("s1024.npy"))
    if not os.path.exists(p("s1024.x3p")):
        subprocess.run([cli, "convert", p("s1024.npy"), p("s1024.x3p"), "--pitch-um", "0.5"], check=True)
    if not os.path.exists(p("s1024_deflated.x3p")):
        with zipfile.ZipFile(p("s1024.x3p")) as src, \
                zipfile.ZipFile(p("s1024_deflated.x3p"), "w", zipfile.ZIP_DEFLATED, compresslevel=6) as dst:
            for info in src.infolist():
                dst.writestr(info.filename, src.read(info.filename))
    if not os.path.exists(p("s1024_f32.datx")):
        write_datx(p("s1024_f32.datx"), z, np.float32, False)
    if not os.path.exists(p("s1024_f64gz.datx")):
        write_datx(p("s1024_f64gz.datx"), z, np.float64, True)
    for name, kind in (("s1024.sur", "plain"), ("s1024c.sur", "compressed")):
        if not os.path.exists(p(name)):
            subprocess.run([bench, "make-sur", p("s1024.npy"), p(name), kind], check=True)
    env = dict(os.environ, SURFSTREAM_REPS=str(a.reps))
    for name in ("s1024.npy", "s1024.x3p", "s1024_deflated.x3p", "s1024_f32.datx", "s1024_f64gz.datx", "s1024.sur", "s1024c.sur"):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        out = subprocess.run([bench, "read", p(name)], env=env, check=True, capture_output=True, text=True).stdout
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        line = json.loads(out.strip().splitlines()[-1])
        line["cpu_s_per_read"] = cpu / (a.reps + 1)
        line["load"] = os.getloadavg()
        if not name.endswith(".npy"):
            tool, med = time_anchor(p(name), a.reps)
            line["anchor"] = {"tool": tool, "median_s": med,
                              "ratio": med / line["read"]["median_s"]}
        print(json.dumps(line))


if __name__ == "__main__":
    main()
