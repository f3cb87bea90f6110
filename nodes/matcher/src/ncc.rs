//! Normalised cross-correlation of levelled heights over the actual overlap of two tiles,
//! valid pixel pairs only.

use crate::plane::PlaneCorrection;
use surfstream_core::avx2_dispatch;
use surfstream_core::raster::RasterView;
use wide::f32x8;

/// A tile levelled on the fly by the plane fitted to its crop: the plane at (row, col) is
/// `row_term[row] + col_term[col]`.
pub(crate) struct LevelledTile<'a> {
    tile: RasterView<'a, f32>,
    row_term: Vec<f32>,
    col_term: Vec<f32>,
}

impl<'a> LevelledTile<'a> {
    /// `plane` as fitted on the crop `rect` (crop-centred coordinates), extended to the tile.
    pub(crate) fn new(
        tile: RasterView<'a, f32>,
        rect: (usize, usize, usize, usize),
        plane: &PlaneCorrection,
    ) -> Self {
        let (x0, y0, w, h) = rect;
        let cx = x0 as f64 + (w as f64 - 1.0) * 0.5;
        let cy = y0 as f64 + (h as f64 - 1.0) * 0.5;
        LevelledTile {
            tile,
            row_term: (0..tile.rows())
                .map(|r| (plane.piston_um + plane.tilt_y_um_per_px * (r as f64 - cy)) as f32)
                .collect(),
            col_term: (0..tile.cols())
                .map(|c| (plane.tilt_x_um_per_px * (c as f64 - cx)) as f32)
                .collect(),
        }
    }
}

/// NCC of the levelled heights of a and b over their actual overlap when b's origin sits at
/// `(dx, dy)` in a's coordinates; valid pairs only. Returns (ncc, pairs).
pub(crate) fn ncc_at(a: &LevelledTile<'_>, b: &LevelledTile<'_>, dx: i64, dy: i64) -> (f64, usize) {
    ncc_in(a, b, dx, dy, overlap_in_a(a, b, dx, dy))
}

/// The overlap `[x0, x1) x [y0, y1)` in a's coordinates when b's origin sits at (dx, dy).
pub(crate) fn overlap_in_a(
    a: &LevelledTile<'_>,
    b: &LevelledTile<'_>,
    dx: i64,
    dy: i64,
) -> [i64; 4] {
    let (wa, ha) = (a.tile.cols() as i64, a.tile.rows() as i64);
    let (wb, hb) = (b.tile.cols() as i64, b.tile.rows() as i64);
    [dx.max(0), (dx + wb).min(wa), dy.max(0), (dy + hb).min(ha)]
}

avx2_dispatch! {
/// [`ncc_at`] restricted to the pixels of a in `region` (`[x0, x1, y0, y1]`, a's coordinates).
pub(crate) fn ncc_in(
    a: &LevelledTile<'_>,
    b: &LevelledTile<'_>,
    dx: i64,
    dy: i64,
    region: [i64; 4],
) -> (f64, usize) {
    let ov = overlap_in_a(a, b, dx, dy);
    let x0 = ov[0].max(region[0]);
    let x1 = ov[1].min(region[1]);
    let y0 = ov[2].max(region[2]);
    let y1 = ov[3].min(region[3]);
    if x1 <= x0 || y1 <= y0 {
        return (0.0, 0);
    }
    let (xa0, xa1) = (x0 as usize, x1 as usize);
    let (xb0, xb1) = ((x0 - dx) as usize, (x1 - dx) as usize);
    let mut acc = [0.0f64; 6];
    for ya in y0..y1 {
        let yb = (ya - dy) as usize;
        let ya = ya as usize;
        let (za, ca, ra) = (
            &a.tile.row(ya)[xa0..xa1],
            &a.col_term[xa0..xa1],
            a.row_term[ya],
        );
        let (zb, cb, rb) = (
            &b.tile.row(yb)[xb0..xb1],
            &b.col_term[xb0..xb1],
            b.row_term[yb],
        );
        let row = row_sums_all_finite(za, ca, ra, zb, cb, rb)
            .unwrap_or_else(|| row_sums(za, ca, ra, zb, cb, rb));
        for (t, v) in acc.iter_mut().zip(row) {
            *t += v as f64;
        }
    }
    finish(acc)
}
}

avx2_dispatch! {
/// NCC of a and b at the 3 x 3 offsets `off + (dx, dy)`, `dx, dy` in -1..=1, all over the
/// pixels of a in `region`, which must lie inside the overlap at every one of the nine
/// offsets (e.g. the overlap at `off` shrunk by 1 px). `c[1 + dy][1 + dx]`. One pass over the
/// rows: a row of a and the three rows of b stay in cache for the nine sums.
///
/// Each of the nine NCCs is taken after removing from both tiles the least-squares plane over
/// that offset's own valid pixel pairs (the residuals' correlation, from the sums below), not
/// the tiles' fixed levelling planes: on a narrow overlap of a surface that is smooth at the
/// pixel scale, a plane fitted at one offset moves the NCC maximum towards that offset (1-3 px
/// on 22-32 px strips of the benchmark's grating).
pub(crate) fn ncc_stencil(
    a: &LevelledTile<'_>,
    b: &LevelledTile<'_>,
    off: [i64; 2],
    region: [i64; 4],
) -> [[f64; 3]; 3] {
    let [x0, x1, y0, y1] = region;
    if x1 <= x0 || y1 <= y0 {
        return [[0.0; 3]; 3];
    }
    let w = (x1 - x0) as usize;
    let h = (y1 - y0) as usize;
    let xa0 = x0 as usize;
    // b's columns for dx = +1 .. -1: [xb0, xb0 + w + 2); its rows for dy = +1 .. -1 at the
    // first row of a onwards: [yb0, yb0 + h + 2).
    let xb0 = (x0 - off[0] - 1) as usize;
    let yb0 = (y0 - off[1] - 1) as usize;
    let wb = w + 2;
    // Plane coordinates centred on the region, so the normal equations stay well conditioned.
    let cx = (w as f32 - 1.0) * 0.5;
    let xs: Vec<f32> = (0..w).map(|i| i as f32 - cx).collect();
    let (sum_x, sum_xx) = xs
        .iter()
        .fold((0.0f32, 0.0f32), |(s, ss), &x| (s + x, ss + x * x));
    let cy = (y0 + y1 - 1) as f64 * 0.5;
    // b levelled once (each of its rows serves three rows of a), NaN kept; rows without NaN
    // get their window sums for the three dx here, so the inner loop is three dot products.
    let mut lb = vec![0.0f32; (h + 2) * wb];
    let mut b_window_sums: Vec<Option<[[f32; 3]; 3]>> = Vec::with_capacity(h + 2);
    for (r, dst) in lb.chunks_exact_mut(wb).enumerate() {
        let yb = yb0 + r;
        let full = level_row_nan(
            &b.tile.row(yb)[xb0..xb0 + wb],
            &b.col_term[xb0..xb0 + wb],
            b.row_term[yb],
            dst,
        );
        b_window_sums.push(full.then(|| window_sums(dst, &xs, cx)));
    }
    let (mut va, mut ma) = (vec![0.0f32; w], vec![0.0f32; w]);
    let (mut vb, mut mb) = (vec![0.0f32; wb], vec![0.0f32; wb]);
    let mut acc = [[[0.0f64; 15]; 3]; 3];
    for (i, ya) in (y0..y1).enumerate() {
        let ya_u = ya as usize;
        let y = ya as f64 - cy;
        let a_full = level_row(
            &a.tile.row(ya_u)[xa0..xa0 + w],
            &a.col_term[xa0..xa0 + w],
            a.row_term[ya_u],
            &mut va,
            &mut ma,
        );
        let a_sums = a_full.then(|| {
            let [s, ss, sx] = weighted_sums(&va, &xs);
            [s as f64, ss as f64, sx as f64]
        });
        for (sy, acc_row) in acc.iter_mut().enumerate() {
            // dy = sy - 1 reads b's row ya - off[1] - dy, buffer row i + 2 - sy.
            let rb = i + 2 - sy;
            let row_b = &lb[rb * wb..(rb + 1) * wb];
            if let (Some([sa, saa, sxa]), Some(bs)) = (a_sums, b_window_sums[rb]) {
                // Every pair valid: n, sum x and sum x^2 are the region's.
                let dots = dot3(&va, row_b);
                for (sx, t) in acc_row.iter_mut().enumerate() {
                    let k = 2 - sx;
                    let (n, sx_, sxx) = (w as f64, sum_x as f64, sum_xx as f64);
                    let [sb, sbb, sxb] = bs[k].map(|v| v as f64);
                    let row = [n, sx_, sxx, sa, sxa, sb, sxb, saa, sbb, dots[k] as f64];
                    add_row_terms(t, y, row);
                }
                continue;
            }
            split_mask(row_b, &mut vb, &mut mb);
            for (sx, t) in acc_row.iter_mut().enumerate() {
                // dx = sx - 1 reads b from index 1 - dx = 2 - sx.
                let k = 2 - sx;
                let r = levelled_sums(&va, &ma, &vb[k..k + w], &mb[k..k + w], &xs);
                let [n, sa, sb, saa, sbb, sab, sx_, sxx, sxa, sxb] = r.map(|v| v as f64);
                add_row_terms(t, y, [n, sx_, sxx, sa, sxa, sb, sxb, saa, sbb, sab]);
            }
        }
    }
    acc.map(|r| r.map(finish_plane_removed))
}
}

/// For a fully valid levelled row of b (`w + 2` values), [sum b, sum b^2, sum x b] over the
/// window `[k, k + w)` for k = 0, 1, 2, with x the plane coordinate of the paired pixel of a
/// (`i - cx` for b's index k + i). The middle `[2, w)` is shared by the three windows and
/// summed once.
#[inline(always)]
fn window_sums(vb: &[f32], xs: &[f32], cx: f32) -> [[f32; 3]; 3] {
    let w = vb.len() - 2;
    // x' = j - 1 - cx (= xs[j - 1]) is the coordinate for window 1; window k's is x' - (k - 1).
    let xp = |j: usize| j as f32 - 1.0 - cx;
    let core = if w > 2 {
        weighted_sums(&vb[2..w], &xs[1..w - 1])
    } else {
        [0.0f32; 3]
    };
    let edge = |js: &[usize]| {
        let mut e = [0.0f32; 3];
        for &j in js {
            let v = vb[j];
            e[0] += v;
            e[1] += v * v;
            e[2] += xp(j) * v;
        }
        e
    };
    // Window k holds [k, k + w): the middle plus k's two edge pixels (w >= 2), or, for w < 2,
    // exactly its own pixels.
    let (two, one) = ([[0, 1], [1, w], [w, w + 1]], [[0], [1], [2]]);
    let edges: [&[usize]; 3] = if w >= 2 {
        [&two[0], &two[1], &two[2]]
    } else {
        [&one[0], &one[1], &one[2]]
    };
    let mut out = [[0.0f32; 3]; 3];
    for (k, js) in edges.into_iter().enumerate() {
        let e = edge(js);
        let sb = core[0] + e[0];
        let sxp = core[2] + e[2];
        out[k] = [sb, core[1] + e[1], sxp - (k as f32 - 1.0) * sb];
    }
    out
}

/// [sum v, sum v^2, sum x v] (no NaN in `v`).
#[inline(always)]
fn weighted_sums(v: &[f32], xs: &[f32]) -> [f32; 3] {
    let mut acc = [f32x8::ZERO; 3];
    let (v8, v_tail) = v.as_chunks::<8>();
    let (x8, x_tail) = xs.as_chunks::<8>();
    for (v, x) in v8.iter().zip(x8) {
        let (v, x) = (f32x8::new(*v), f32x8::new(*x));
        acc[0] += v;
        acc[1] += v * v;
        acc[2] += x * v;
    }
    let mut t = acc.map(|a| a.to_array().iter().sum::<f32>());
    for (&v, &x) in v_tail.iter().zip(x_tail) {
        t[0] += v;
        t[1] += v * v;
        t[2] += x * v;
    }
    t
}

/// `sum a[i] b[i + k]` for k = 0, 1, 2 (`b.len() >= a.len() + 2`), in one pass over a.
#[inline(always)]
fn dot3(a: &[f32], b: &[f32]) -> [f32; 3] {
    let n = a.len();
    let mut acc = [f32x8::ZERO; 3];
    let chunks = n / 8;
    for c in 0..chunks {
        let o = c * 8;
        let av = f32x8::new(a[o..o + 8].try_into().unwrap_or([0.0; 8]));
        let b10 = &b[o..o + 10];
        for (k, acc) in acc.iter_mut().enumerate() {
            *acc += av * f32x8::new(b10[k..k + 8].try_into().unwrap_or([0.0; 8]));
        }
    }
    let mut t = acc.map(|x| x.to_array().iter().sum::<f32>());
    for i in chunks * 8..n {
        t[0] += a[i] * b[i];
        t[1] += a[i] * b[i + 1];
        t[2] += a[i] * b[i + 2];
    }
    t
}

/// Adds one row's sums at plane coordinate `y`, `[n, Sx, Sxx, Sa, Sxa, Sb, Sxb, Saa, Sbb,
/// Sab]`, to the 15 sums [`finish_plane_removed`] takes.
#[inline(always)]
fn add_row_terms(t: &mut [f64; 15], y: f64, row: [f64; 10]) {
    let [n, sx, sxx, sa, sxa, sb, sxb, saa, sbb, sab] = row;
    let add = [
        n,
        sx,
        y * n,
        sxx,
        y * sx,
        y * y * n,
        sa,
        sxa,
        y * sa,
        sb,
        sxb,
        y * sb,
        saa,
        sbb,
        sab,
    ];
    for (u, v) in t.iter_mut().zip(add) {
        *u += v;
    }
}

/// NCC of the residuals after removing each side's least-squares plane over the common valid
/// pixels, from [n, Sx, Sy, Sxx, Sxy, Syy, Sa, Sxa, Sya, Sb, Sxb, Syb, Saa, Sbb, Sab]: with
/// G the Gram matrix of (1, x, y) and u_a = (Sa, Sxa, Sya), the residual products are
/// `Sab - u_a' G^-1 u_b` (and likewise for a, a and b, b).
fn finish_plane_removed(s: [f64; 15]) -> f64 {
    let [n, sx, sy, sxx, sxy, syy, sa, sxa, sya, sb, sxb, syb, saa, sbb, sab] = s;
    if n < 4.0 {
        return 0.0;
    }
    let g = nalgebra::Matrix3::new(n, sx, sy, sx, sxx, sxy, sy, sxy, syy);
    let ua = nalgebra::Vector3::new(sa, sxa, sya);
    let ub = nalgebra::Vector3::new(sb, sxb, syb);
    let Some(chol) = g.cholesky() else {
        // The valid pixels lie on a line: only the piston can be removed.
        return finish([n, sa, sb, saa, sbb, sab]).0;
    };
    let ga = chol.solve(&ua);
    let gb = chol.solve(&ub);
    let vaa = saa - ua.dot(&ga);
    let vbb = sbb - ub.dot(&gb);
    let cov = sab - ua.dot(&gb);
    let den = (vaa * vbb).sqrt();
    if den > 0.0 && den.is_finite() {
        (cov / den).clamp(-1.0, 1.0)
    } else {
        0.0
    }
}

/// `v = z - (r + c)` where finite (mask 1), else 0 (mask 0); true when every value is finite.
#[inline(always)]
fn level_row(z: &[f32], c: &[f32], r: f32, v: &mut [f32], m: &mut [f32]) -> bool {
    let mut valid = 0.0f32;
    for (((v, m), &z), &c) in v.iter_mut().zip(m.iter_mut()).zip(z).zip(c) {
        let x = z - (r + c);
        let ok = x.is_finite();
        *v = if ok { x } else { 0.0 };
        *m = if ok { 1.0 } else { 0.0 };
        valid += *m;
    }
    valid as usize == v.len()
}

/// `v = z - (r + c)`, NaN where z is not finite; true when every value is finite.
#[inline(always)]
fn level_row_nan(z: &[f32], c: &[f32], r: f32, v: &mut [f32]) -> bool {
    let mut invalid = 0usize;
    for ((v, &z), &c) in v.iter_mut().zip(z).zip(c) {
        let x = z - (r + c);
        invalid += usize::from(!x.is_finite());
        *v = x;
    }
    invalid == 0
}

/// Splits a levelled row (NaN = invalid) into values (0 where invalid) and 0/1 masks.
#[inline(always)]
fn split_mask(src: &[f32], v: &mut [f32], m: &mut [f32]) {
    for ((v, m), &x) in v.iter_mut().zip(m.iter_mut()).zip(src) {
        let ok = x.is_finite();
        *v = if ok { x } else { 0.0 };
        *m = if ok { 1.0 } else { 0.0 };
    }
}

/// [n, sum a, sum b, sum a^2, sum b^2, sum ab, sum x, sum x^2, sum x a, sum x b] over pairs
/// valid in both of two levelled rows (values 0 where invalid, masks 0/1; `xs` the plane
/// coordinate of each column).
#[inline(always)]
fn levelled_sums(va: &[f32], ma: &[f32], vb: &[f32], mb: &[f32], xs: &[f32]) -> [f32; 10] {
    const L: usize = 4;
    let mut acc = [[0.0f32; L]; 10];
    let lane = |acc: &mut [[f32; L]; 10], l: usize, va: f32, ma: f32, vb: f32, mb: f32, x: f32| {
        let m = ma * mb;
        let am = va * mb;
        let bm = vb * ma;
        acc[0][l] += m;
        acc[1][l] += am;
        acc[2][l] += bm;
        acc[3][l] += va * am;
        acc[4][l] += vb * bm;
        acc[5][l] += va * vb;
        acc[6][l] += x * m;
        acc[7][l] += x * x * m;
        acc[8][l] += x * am;
        acc[9][l] += x * bm;
    };
    let (va4, _) = va.as_chunks::<L>();
    let (ma4, _) = ma.as_chunks::<L>();
    let (vb4, _) = vb.as_chunks::<L>();
    let (mb4, _) = mb.as_chunks::<L>();
    let (xs4, _) = xs.as_chunks::<L>();
    for ((((va, ma), vb), mb), xs) in va4.iter().zip(ma4).zip(vb4).zip(mb4).zip(xs4) {
        for l in 0..L {
            lane(&mut acc, l, va[l], ma[l], vb[l], mb[l], xs[l]);
        }
    }
    let tail = va.len() - va.len() % L;
    for i in tail..va.len() {
        lane(&mut acc, 0, va[i], ma[i], vb[i], mb[i], xs[i]);
    }
    acc.map(|x| x.iter().sum::<f32>())
}

/// NCC and pair count from [n, sum a, sum b, sum a^2, sum b^2, sum ab].
fn finish(acc: [f64; 6]) -> (f64, usize) {
    let [n, sa, sb, saa, sbb, sab] = acc;
    if n < 2.0 {
        return (0.0, n as usize);
    }
    let va = saa - sa * sa / n;
    let vb = sbb - sb * sb / n;
    let cov = sab - sa * sb / n;
    let den = (va * vb).sqrt();
    let ncc = if den > 0.0 && den.is_finite() {
        (cov / den).clamp(-1.0, 1.0)
    } else {
        0.0
    };
    (ncc, n as usize)
}

/// [`row_sums`] when every pixel of both rows is valid (checked on the sums, into which a NaN
/// or infinity propagates), else `None`: no masks, five lanes instead of six.
#[inline(always)]
fn row_sums_all_finite(
    za: &[f32],
    ca: &[f32],
    ra: f32,
    zb: &[f32],
    cb: &[f32],
    rb: f32,
) -> Option<[f32; 6]> {
    let (za8, za_t) = za.as_chunks::<8>();
    let (ca8, ca_t) = ca.as_chunks::<8>();
    let (zb8, zb_t) = zb.as_chunks::<8>();
    let (cb8, cb_t) = cb.as_chunks::<8>();
    let (rav, rbv) = (f32x8::splat(ra), f32x8::splat(rb));
    let mut acc = [f32x8::ZERO; 5];
    for (((za, ca), zb), cb) in za8.iter().zip(ca8).zip(zb8).zip(cb8) {
        let a = f32x8::new(*za) - (rav + f32x8::new(*ca));
        let b = f32x8::new(*zb) - (rbv + f32x8::new(*cb));
        acc[0] += a;
        acc[1] += b;
        acc[2] += a * a;
        acc[3] += b * b;
        acc[4] += a * b;
    }
    let mut t = acc.map(|v| v.to_array().iter().sum::<f32>());
    for (((za, ca), zb), cb) in za_t.iter().zip(ca_t).zip(zb_t).zip(cb_t) {
        let a = za - (ra + ca);
        let b = zb - (rb + cb);
        t[0] += a;
        t[1] += b;
        t[2] += a * a;
        t[3] += b * b;
        t[4] += a * b;
    }
    let [sa, sb, saa, sbb, sab] = t;
    t.iter()
        .all(|v| v.is_finite())
        .then_some([za.len() as f32, sa, sb, saa, sbb, sab])
}

/// [n, sum a, sum b, sum a^2, sum b^2, sum ab] of the levelled rows `a = za - (ra + ca)`,
/// `b = zb - (rb + cb)` over pairs valid (finite) in both; branch-free lanes so the compiler
/// vectorises it.
#[inline(always)]
fn row_sums(za: &[f32], ca: &[f32], ra: f32, zb: &[f32], cb: &[f32], rb: f32) -> [f32; 6] {
    const L: usize = 8;
    let mut acc = [[0.0f32; L]; 6];
    let lane = |acc: &mut [[f32; L]; 6], l: usize, za: f32, ca: f32, zb: f32, cb: f32| {
        let a = za - (ra + ca);
        let b = zb - (rb + cb);
        let oka = a.is_finite();
        let okb = b.is_finite();
        let ma = if oka { 1.0 } else { 0.0 };
        let mb = if okb { 1.0 } else { 0.0 };
        let a = if oka { a } else { 0.0 };
        let b = if okb { b } else { 0.0 };
        let am = a * mb;
        let bm = b * ma;
        acc[0][l] += ma * mb;
        acc[1][l] += am;
        acc[2][l] += bm;
        acc[3][l] += a * am;
        acc[4][l] += b * bm;
        acc[5][l] += a * b;
    };
    let n = za.len();
    let chunks = n / L;
    for k in 0..chunks {
        let o = k * L;
        let (za, ca, zb, cb) = (&za[o..o + L], &ca[o..o + L], &zb[o..o + L], &cb[o..o + L]);
        for l in 0..L {
            lane(&mut acc, l, za[l], ca[l], zb[l], cb[l]);
        }
    }
    for i in chunks * L..n {
        lane(&mut acc, 0, za[i], ca[i], zb[i], cb[i]);
    }
    let mut out = [0.0f32; 6];
    for (o, a) in out.iter_mut().zip(&acc) {
        *o = a.iter().sum();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::raster::Shape;

    /// Reference for the stencil: NCC after removing each side's plane over the pairs valid
    /// in both, in f64 with nalgebra's least squares.
    fn plane_removed_ncc(
        za: &[f32],
        zb: &[f32],
        w: usize,
        dx: i64,
        dy: i64,
        region: [i64; 4],
    ) -> f64 {
        let mut rows = Vec::new();
        for ya in region[2]..region[3] {
            for xa in region[0]..region[1] {
                let a = za[ya as usize * w + xa as usize];
                let b = zb[(ya - dy) as usize * w + (xa - dx) as usize];
                if a.is_finite() && b.is_finite() {
                    rows.push((xa as f64, ya as f64, a as f64, b as f64));
                }
            }
        }
        let m = nalgebra::DMatrix::from_fn(rows.len(), 3, |i, j| match j {
            0 => 1.0,
            1 => rows[i].0,
            _ => rows[i].1,
        });
        let resid = |col: usize| {
            let z = nalgebra::DVector::from_fn(rows.len(), |i, _| {
                if col == 0 {
                    rows[i].2
                } else {
                    rows[i].3
                }
            });
            let c = m
                .clone()
                .svd(true, true)
                .solve(&z, 1e-12)
                .expect("least squares");
            z - &m * c
        };
        let (ra, rb) = (resid(0), resid(1));
        ra.dot(&rb) / (ra.norm() * rb.norm())
    }

    #[test]
    fn ncc_of_identical_tiles_is_one_and_ignores_plane_and_nan() {
        let (w, h) = (40, 30);
        let mut za: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 17) as f32).collect();
        let mut zb: Vec<f32> = za
            .iter()
            .enumerate()
            .map(|(i, v)| v + 3.0 + 0.01 * (i % w) as f32)
            .collect();
        za[5] = f32::NAN;
        zb[77] = f32::NAN;
        let ta = RasterView::new(&za, Shape::new(h, w)).expect("valid");
        let tb = RasterView::new(&zb, Shape::new(h, w)).expect("valid");
        let rect = (0, 0, w, h);
        let la = LevelledTile::new(ta, rect, &PlaneCorrection::ZERO);
        let plane_b = PlaneCorrection {
            piston_um: 3.0 + 0.01 * (w as f64 - 1.0) / 2.0,
            tilt_x_um_per_px: 0.01,
            tilt_y_um_per_px: 0.0,
        };
        let lb = LevelledTile::new(tb, rect, &plane_b);
        let (ncc, n) = ncc_at(&la, &lb, 0, 0);
        assert_eq!(n, w * h - 2);
        assert!((ncc - 1.0).abs() < 1e-6, "{ncc}");
        // The stencil agrees with a direct f64 computation: at each offset, both sides'
        // least-squares planes over the common valid pixels removed, then the NCC.
        let region = [2, w as i64 - 2, 2, h as i64 - 2];
        let st = ncc_stencil(&la, &lb, [0, 0], region);
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                let direct = plane_removed_ncc(&za, &zb, w, dx, dy, region);
                let s = st[(dy + 1) as usize][(dx + 1) as usize];
                assert!((direct - s).abs() < 1e-5, "{dx} {dy}: {direct} vs {s}");
            }
        }
        // Shifted by 3 px: overlap shrinks accordingly.
        let (_, n3) = ncc_at(&la, &lb, 3, -2);
        assert!(n3 <= (w - 3) * (h - 2));
    }

    /// The AVX2 and baseline copies of the NCC kernels give bit-identical answers, on rows
    /// with and without dropouts, and both agree with the f64 reference.
    #[test]
    fn avx2_and_baseline_kernels_agree_bit_for_bit() {
        let (w, h) = (203, 61);
        let height = |i: usize| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            (0.13 * x).sin() * 0.7 + (0.071 * y + 0.02 * x).cos() * 0.4 + 0.001 * x
        };
        let za: Vec<f32> = (0..w * h)
            .map(|i| if i % 997 == 5 { f32::NAN } else { height(i) })
            .collect();
        let zb: Vec<f32> = (0..w * h).map(|i| height(i + 2 * w + 3) + 0.5).collect();
        let ta = RasterView::new(&za, Shape::new(h, w)).expect("valid");
        let tb = RasterView::new(&zb, Shape::new(h, w)).expect("valid");
        let la = LevelledTile::new(ta, (0, 0, w, h), &PlaneCorrection::ZERO);
        let lb = LevelledTile::new(tb, (0, 0, w, h), &PlaneCorrection::ZERO);
        let region = [5, w as i64 - 5, 5, h as i64 - 5];
        let fast = (
            ncc_stencil(&la, &lb, [-3, -2], region),
            ncc_at(&la, &lb, -3, -2),
        );
        let base = surfstream_core::simd::with_baseline(|| {
            (
                ncc_stencil(&la, &lb, [-3, -2], region),
                ncc_at(&la, &lb, -3, -2),
            )
        });
        assert_eq!(fast.1, base.1);
        for (f, b) in fast.0.iter().flatten().zip(base.0.iter().flatten()) {
            assert_eq!(f.to_bits(), b.to_bits(), "{f} vs {b}");
        }
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                let direct = plane_removed_ncc(&za, &zb, w, -3 + dx, -2 + dy, region);
                let s = fast.0[(dy + 1) as usize][(dx + 1) as usize];
                assert!((direct - s).abs() < 1e-5, "{dx} {dy}: {direct} vs {s}");
            }
        }
    }
}
