//! Functional parameters from the areal material ratio (Abbott-Firestone) curve, ISO 25178-2
//! §4.5 and Annex B (the Sk family after ISO 13565-2): Sk, Spk, Svk, Smr1, Smr2, Spkx, Svkx,
//! Sak1, Sak2, Sxp, Vmp, Vmc, Vvv, Vvc, Smr(c), Smc(mr).
//!
//! The curve: heights as a function of the material ratio mr (0 % at the highest point, 100 %
//! at the lowest), sampled at [`CURVE_SAMPLES`] ratios equally spaced in mr: height(mr) = the
//! (1 - mr/100) quantile of the valid heights, linearly interpolated between order statistics
//! (numpy's default quantile, the parity reference surfalize 0.19.2 samples the same way). The
//! heights are about the mean of the valid points (c = 0 is the mean plane).
//!
//! The equivalent straight line (ISO 25178-2 B.1 / ISO 13565-2 §4.3): first the central region,
//! the 40 % wide window of mr whose secant has the least (absolute) gradient, the first such
//! window on ties; then the least-squares line (deviations in height) through the curve points
//! inside that window. Sk is that line's height difference between mr = 0 % and 100 %; Smr1
//! and Smr2 the material ratios at those two heights; Spk and Svk the heights of the triangles
//! with the areas of the peaks above / dales below the core (Sak1, Sak2). A line taken as the
//! secant alone, or fitted to an equal-height histogram, comes out steeper on skewed data:
//! see the tests for the reference computation.
//!
//! Volume parameters (ml/m^2 = um^3/um^2): Vm(p) = integral over mr in [0, p] of
//! (height(mr) - height(p)) / 100, Vv(p) = integral over [p, 100] of (height(p) - height(mr)) /
//! 100; Vmp = Vm(10 %), Vmc = Vm(80 %) - Vm(10 %), Vvv = Vv(80 %), Vvc = Vv(10 %) - Vv(80 %).
//! Sxp = Smc(2.5 %) - Smc(50 %). The integrals are trapezoids over the sampled curve, cut at
//! the sample nearest to the limit, as surfalize does (the difference to the exact integral is
//! below one sample step, 0.01 % of the height range).
//!
//! NaN: only valid points enter the curve (the material ratio is a fraction of the measured
//! area).

use rayon::prelude::*;
use serde::Serialize;

use super::{Grid, MetrologyError};

/// Samples of the material ratio curve (equally spaced in mr, 0 and 100 % included).
pub const CURVE_SAMPLES: usize = 10_000;
/// Width of the central region of the equivalent straight line, in % of material ratio.
const CORE_WIDTH_PCT: f64 = 40.0;

/// The sampled material ratio curve and its equivalent straight line.
#[derive(Debug, Clone)]
pub struct AbbottCurve {
    /// Material ratio in %, ascending, 0..=100.
    pub material_ratio_pct: Vec<f64>,
    /// Height in um about the mean of the valid points, descending.
    pub height_um: Vec<f64>,
    /// The equivalent straight line height = slope * mr + intercept (um, mr in %).
    pub line_slope_um_per_pct: f64,
    pub line_intercept_um: f64,
    /// Start of the 40 % central region (%).
    pub core_start_pct: f64,
    max_um: f64,
    min_um: f64,
}

/// The functional parameters; heights in um, ratios in %, volumes in ml/m^2, areas (Sak) in
/// um * %.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FunctionalParams {
    #[serde(rename = "Sk")]
    pub sk: f64,
    #[serde(rename = "Spk")]
    pub spk: f64,
    #[serde(rename = "Svk")]
    pub svk: f64,
    #[serde(rename = "Smr1")]
    pub smr1: f64,
    #[serde(rename = "Smr2")]
    pub smr2: f64,
    #[serde(rename = "Spkx")]
    pub spkx: f64,
    #[serde(rename = "Svkx")]
    pub svkx: f64,
    #[serde(rename = "Sak1")]
    pub sak1: f64,
    #[serde(rename = "Sak2")]
    pub sak2: f64,
    #[serde(rename = "Sxp")]
    pub sxp: f64,
    #[serde(rename = "Vmp")]
    pub vmp: f64,
    #[serde(rename = "Vmc")]
    pub vmc: f64,
    #[serde(rename = "Vvv")]
    pub vvv: f64,
    #[serde(rename = "Vvc")]
    pub vvc: f64,
}

/// numpy's linear interpolation between two order statistics (its `_lerp`, symmetric in t).
fn lerp(a: f64, b: f64, t: f64) -> f64 {
    let d = b - a;
    if t >= 0.5 {
        b - d * (1.0 - t)
    } else {
        a + d * t
    }
}

/// np.interp on ascending `xp`: clamps outside, linear inside (right-most equal xp wins).
fn interp(x: f64, xp: &[f64], fp: &[f64]) -> f64 {
    let n = xp.len();
    if n == 0 || x.is_nan() {
        return f64::NAN;
    }
    if x <= xp[0] {
        return fp[0];
    }
    if x >= xp[n - 1] {
        return fp[n - 1];
    }
    // First index with xp[j] > x.
    let j = xp.partition_point(|&v| v <= x);
    let i = j - 1;
    let (x0, x1) = (xp[i], xp[j]);
    if x1 == x0 {
        return fp[i];
    }
    let s = (fp[j] - fp[i]) / (x1 - x0);
    s * (x - x0) + fp[i]
}

/// Trapezoid integral of y over x (x may descend: the sign follows).
fn trapezoid(y: &[f64], x: &[f64]) -> f64 {
    y.windows(2)
        .zip(x.windows(2))
        .map(|(yy, xx)| (xx[1] - xx[0]) * (yy[0] + yy[1]) * 0.5)
        .sum()
}

/// The valid heights of `g`, ascending, and their mean.
fn sorted_valid(g: &Grid) -> Result<(Vec<f64>, f64), MetrologyError> {
    let mut v: Vec<f64> = g
        .heights_um
        .par_iter()
        .copied()
        .filter(|z| !z.is_nan())
        .collect();
    if v.is_empty() {
        return Err(MetrologyError::NoValidPoint);
    }
    // Radix sort: the order of f64::total_cmp (NaN were left out above), in a few passes.
    radsort::sort(&mut v);
    let mean = super::height_params_mean(g)?;
    Ok((v, mean))
}

/// The `samples` (>= 2) material ratios of the curve, %: equally spaced, 0 and 100 exact.
fn ratios(samples: usize) -> Vec<f64> {
    let samples = samples.max(2);
    let step = 100.0 / (samples - 1) as f64;
    let mut mr: Vec<f64> = (0..samples).map(|i| i as f64 * step).collect();
    mr[samples - 1] = 100.0;
    mr
}

/// The two order statistics (ranks, ascending) of `n` heights the curve interpolates at
/// material ratio `m` %, and the fraction between them: quantile q = 1 - m/100, virtual
/// index q (n - 1) (numpy's "linear").
fn sample_ranks(m: f64, n: usize) -> (usize, usize, f64) {
    let q = 1.0 - m / 100.0;
    let idx = q * (n - 1) as f64;
    let lo = (idx.floor() as usize).min(n - 1);
    let hi = (lo + 1).min(n - 1);
    (lo, hi, idx - lo as f64)
}

/// Buckets of [`order_statistics`]' histogram.
const BUCKETS: usize = 1 << 20;

/// The values at `ranks` (ascending, distinct, each < `n`) in the ascending order of
/// `f64::total_cmp` of the `n` valid (non-NaN) values of `z`: what a full sort would hold
/// there. One pass counts the values in equal-width buckets of their range (a bucket's
/// values are all below the next bucket's: the bucket index is monotone in the value, and
/// -0 and +0 share one); a second gathers the values of the buckets holding a wanted rank,
/// which are then sorted by `total_cmp` (a few per rank instead of the whole map).
pub(crate) fn order_statistics(z: &[f64], n: usize, ranks: &[usize]) -> Vec<f64> {
    let (lo, hi) = z
        .par_iter()
        .filter(|v| !v.is_nan())
        .fold(
            || (f64::INFINITY, f64::NEG_INFINITY),
            |(a, b), &v| (a.min(v), b.max(v)),
        )
        .reduce(
            || (f64::INFINITY, f64::NEG_INFINITY),
            |(a, b), (c, d)| (a.min(c), b.max(d)),
        );
    let scale = BUCKETS as f64 / (hi - lo);
    // A zero or infinite range: one bucket (then all the values are gathered).
    let one = !(scale.is_finite() && scale > 0.0);
    let bucket = |v: f64| -> usize {
        if one {
            0
        } else {
            (((v - lo) * scale) as usize).min(BUCKETS - 1)
        }
    };
    let parts = rayon::current_num_threads().max(1);
    let chunk = z.len().div_ceil(parts).max(1);
    let count = z
        .par_chunks(chunk)
        .map(|part| {
            let mut c = vec![0u32; BUCKETS];
            for &v in part {
                if !v.is_nan() {
                    c[bucket(v)] += 1;
                }
            }
            c
        })
        .reduce_with(|mut a, b| {
            for (x, y) in a.iter_mut().zip(&b) {
                *x += y;
            }
            a
        })
        .unwrap_or_else(|| vec![0u32; BUCKETS]);
    // The buckets holding a wanted rank, with their first and end ranks.
    let mut wanted = vec![false; BUCKETS];
    let mut spans: Vec<(usize, usize)> = Vec::new();
    let (mut start, mut r) = (0usize, 0usize);
    for (b, &c) in count.iter().enumerate() {
        let end = start + c as usize;
        if r < ranks.len() && ranks[r] < end {
            wanted[b] = true;
            spans.push((start, end));
            while r < ranks.len() && ranks[r] < end {
                r += 1;
            }
        }
        start = end;
    }
    debug_assert_eq!(start, n);
    drop(count);
    let mut gathered: Vec<f64> = z
        .par_iter()
        .copied()
        .filter(|&v| !v.is_nan() && wanted[bucket(v)])
        .collect();
    gathered.par_sort_unstable_by(f64::total_cmp);
    // Rank k of a wanted bucket [s, e) sits at k - s after the values gathered before it.
    let (mut offset, mut r) = (0usize, 0usize);
    let mut out = Vec::with_capacity(ranks.len());
    for (s, e) in spans {
        while r < ranks.len() && ranks[r] < e {
            out.push(gathered[offset + ranks[r] - s]);
            r += 1;
        }
        offset += e - s;
    }
    out
}

impl AbbottCurve {
    /// The curve of the valid heights of `g` about their mean.
    ///
    /// Only the order statistics the samples use are found ([`order_statistics`]), not the
    /// whole sort: the same values, without a sorted copy of the map.
    pub fn of(g: &Grid) -> Result<Self, MetrologyError> {
        let mean = super::height_params_mean(g)?;
        let n = g.heights_um.par_iter().filter(|z| !z.is_nan()).count();
        if n == 0 {
            return Err(MetrologyError::NoValidPoint);
        }
        let samples = CURVE_SAMPLES;
        let mut ranks: Vec<usize> = vec![0, n - 1];
        for m in ratios(samples) {
            let (lo, hi, _) = sample_ranks(m, n);
            ranks.extend([lo, hi]);
        }
        ranks.sort_unstable();
        ranks.dedup();
        let values = order_statistics(g.heights_um, n, &ranks);
        let at = |k: usize| values[ranks.partition_point(|&r| r < k)];
        Ok(Self::from_order(n, &at, mean, samples))
    }

    /// The curve from heights sorted ascending, about `mean`, with `samples` >= 2 points.
    pub fn from_sorted(sorted: &[f64], mean: f64, samples: usize) -> Self {
        Self::from_order(sorted.len(), &|k| sorted[k], mean, samples)
    }

    /// The curve from `n` heights whose k-th smallest is `at(k)` (only the ranks of
    /// [`sample_ranks`], 0 and n - 1 are asked).
    fn from_order(n: usize, at: &dyn Fn(usize) -> f64, mean: f64, samples: usize) -> Self {
        let samples = samples.max(2);
        let mr = ratios(samples);
        let height: Vec<f64> = mr
            .iter()
            .map(|&m| {
                let (lo, hi, t) = sample_ranks(m, n);
                lerp(at(lo), at(hi), t) - mean
            })
            .collect();
        // Heights ascending with their ratios, for mr(c) (the curve descends in mr).
        let mut c = Self {
            material_ratio_pct: mr,
            height_um: height,
            line_slope_um_per_pct: f64::NAN,
            line_intercept_um: f64::NAN,
            core_start_pct: f64::NAN,
            max_um: at(n - 1) - mean,
            min_um: at(0) - mean,
        };
        c.fit_line();
        c
    }

    /// Height at material ratio `mr_pct` (Smc(mr)), um about the mean.
    pub fn smc(&self, mr_pct: f64) -> f64 {
        interp(mr_pct, &self.material_ratio_pct, &self.height_um)
    }

    /// Material ratio (%) at height `c_um` about the mean (Smr(c)).
    pub fn smr(&self, c_um: f64) -> f64 {
        // Ascending heights: the curve reversed.
        let n = self.height_um.len();
        let h = |i: usize| self.height_um[n - 1 - i];
        if c_um.is_nan() {
            return f64::NAN;
        }
        if c_um <= h(0) {
            return self.material_ratio_pct[n - 1];
        }
        if c_um >= h(n - 1) {
            return self.material_ratio_pct[0];
        }
        // First ascending index with height > c.
        let (mut lo, mut hi) = (0usize, n);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if h(mid) <= c_um {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        let j = lo;
        let i = j - 1;
        let (x0, x1) = (h(i), h(j));
        let (f0, f1) = (
            self.material_ratio_pct[n - 1 - i],
            self.material_ratio_pct[n - 1 - j],
        );
        if x1 == x0 {
            return f0;
        }
        (f1 - f0) / (x1 - x0) * (c_um - x0) + f0
    }

    fn fit_line(&mut self) {
        let mr = &self.material_ratio_pct;
        let h = &self.height_um;
        // Step 1: the 40 % window whose secant is least steep (slopes are <= 0: the largest).
        let mut best: Option<(f64, usize)> = None;
        for (i, &m) in mr.iter().enumerate() {
            if m > 100.0 - CORE_WIDTH_PCT {
                break;
            }
            let slope = (self.smc(m + CORE_WIDTH_PCT) - h[i]) / CORE_WIDTH_PCT;
            match best {
                None => best = Some((slope, i)),
                Some((s, _)) if slope > s => best = Some((slope, i)),
                _ => {}
            }
        }
        let start = best.map_or(0, |b| b.1);
        let m0 = mr[start];
        let end = mr.partition_point(|&v| v <= m0 + CORE_WIDTH_PCT);
        // Step 2: least squares through the points of the window (centred sums).
        let (xs, ys) = (&mr[start..end], &h[start..end]);
        let k = xs.len() as f64;
        let xm = xs.iter().sum::<f64>() / k;
        let ym = ys.iter().sum::<f64>() / k;
        let (mut sxx, mut sxy) = (0.0, 0.0);
        for (&x, &y) in xs.iter().zip(ys) {
            sxx += (x - xm) * (x - xm);
            sxy += (x - xm) * (y - ym);
        }
        let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
        self.line_slope_um_per_pct = slope;
        self.line_intercept_um = ym - slope * xm;
        self.core_start_pct = m0;
    }

    /// Heights of the equivalent line at mr = 0 % and 100 % (um).
    pub fn core_limits_um(&self) -> (f64, f64) {
        let upper = self.line_intercept_um;
        (upper, self.line_slope_um_per_pct * 100.0 + upper)
    }

    fn closest(&self, c: f64) -> usize {
        let mut best = (f64::INFINITY, 0);
        for (i, &h) in self.height_um.iter().enumerate() {
            let d = (h - c).abs();
            if d < best.0 {
                best = (d, i);
            }
        }
        best.1
    }

    /// Material volume at ratio p (ml/m^2).
    pub fn vm(&self, p_pct: f64) -> f64 {
        let idx = self.closest(self.smc(p_pct));
        trapezoid(&self.material_ratio_pct[..idx], &self.height_um[..idx]).abs() / 100.0
    }

    /// Void volume at ratio p (ml/m^2).
    pub fn vv(&self, p_pct: f64) -> f64 {
        let idx = self.closest(self.smc(p_pct));
        let y: Vec<f64> = self.material_ratio_pct[idx..]
            .iter()
            .map(|m| 100.0 - m)
            .collect();
        trapezoid(&y, &self.height_um[idx..]).abs() / 100.0
    }

    /// All functional parameters.
    pub fn params(&self) -> FunctionalParams {
        let (upper, lower) = self.core_limits_um();
        let smr1 = self.smr(upper);
        let smr2 = self.smr(lower);
        let iu = self.closest(upper);
        let sak1 = trapezoid(&self.material_ratio_pct[..iu], &self.height_um[..iu]).abs();
        let il = self.closest(lower);
        let y: Vec<f64> = self.material_ratio_pct[il..]
            .iter()
            .map(|m| 100.0 - m)
            .collect();
        let sak2 = trapezoid(&y, &self.height_um[il..]).abs();
        FunctionalParams {
            sk: upper - lower,
            spk: if sak1 > 0.0 { 2.0 * sak1 / smr1 } else { 0.0 },
            svk: if sak2 > 0.0 {
                2.0 * sak2 / (100.0 - smr2)
            } else {
                0.0
            },
            smr1,
            smr2,
            spkx: self.max_um - upper,
            svkx: lower - self.min_um,
            sak1,
            sak2,
            sxp: self.smc(2.5) - self.smc(50.0),
            vmp: self.vm(10.0),
            vmc: self.vm(80.0) - self.vm(10.0),
            vvv: self.vv(80.0),
            vvc: self.vv(10.0) - self.vv(80.0),
        }
    }

    /// (material ratio %, height um) pairs of the sampled curve, for plots.
    pub fn points(&self) -> Vec<(f64, f64)> {
        self.material_ratio_pct
            .iter()
            .copied()
            .zip(self.height_um.iter().copied())
            .collect()
    }
}

/// The Abbott-Firestone curve of `g`'s valid heights about their mean, `samples` points of
/// (material ratio %, height um), for the report's plot.
pub fn abbott_curve(g: &Grid, samples: usize) -> Result<Vec<(f64, f64)>, MetrologyError> {
    let (sorted, mean) = sorted_valid(g)?;
    Ok(AbbottCurve::from_sorted(&sorted, mean, samples).points())
}

/// The functional parameters of `g` (see the module documentation).
pub fn functional_params(g: &Grid) -> Result<FunctionalParams, MetrologyError> {
    Ok(AbbottCurve::of(g)?.params())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bucketed order statistics are the full sort's, bit for bit: ties, -0 and +0,
    /// NaN left out, a constant map (zero range), an infinite range.
    #[test]
    fn order_statistics_are_the_sorts() {
        let mut state = 0x2545_F491_4F6C_DD1D_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut v: Vec<f64> = (0..200_000)
            .map(|i| match i % 5 {
                0 => (next() % 41) as f64 - 20.0,
                1 => f64::NAN,
                2 if i % 10 == 2 => -0.0,
                2 => 0.0,
                _ => (next() as f64 / u64::MAX as f64 - 0.3) * 1e-3,
            })
            .collect();
        let check = |v: &[f64]| {
            let mut sorted: Vec<f64> = v.iter().copied().filter(|z| !z.is_nan()).collect();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len();
            let ranks: Vec<usize> = (0..n).step_by(7).chain([n - 1]).collect();
            let got = order_statistics(v, n, &ranks);
            let want: Vec<u64> = ranks.iter().map(|&k| sorted[k].to_bits()).collect();
            assert_eq!(got.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), want);
        };
        check(&v);
        check(&[3.5; 1000]);
        check(&[0.0, -0.0, 0.0, -0.0, f64::NAN]);
        v.push(f64::INFINITY);
        v.push(f64::NEG_INFINITY);
        check(&v);
    }

    /// The curve from the order statistics is the curve from the full sort.
    #[test]
    fn curve_of_grid_is_the_sorted_curve() {
        let (rows, cols) = (97, 131);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f64, (i % cols) as f64);
                if i % 17 == 3 {
                    f64::NAN
                } else {
                    (r * 0.37).sin() * 2.0 + (c * 0.11).cos() + ((i * 7919) % 101) as f64 * 1e-3
                }
            })
            .collect();
        let g = Grid::new(&z, rows, cols, 0.5, 0.7).unwrap();
        let (sorted, mean) = sorted_valid(&g).unwrap();
        let a = AbbottCurve::of(&g).unwrap();
        let b = AbbottCurve::from_sorted(&sorted, mean, CURVE_SAMPLES);
        let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.height_um), bits(&b.height_um));
        assert_eq!(a.params(), b.params());
        assert_eq!(a.max_um.to_bits(), b.max_um.to_bits());
        assert_eq!(a.min_um.to_bits(), b.min_um.to_bits());
    }

    /// The radix sort gives the order of `f64::total_cmp` (signs, zeros, infinities,
    /// subnormals, ties), so the material ratio curve is the comparison sort's.
    #[test]
    fn radix_sort_orders_as_total_cmp() {
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut v: Vec<f64> = (0..100_000)
            .map(|i| match i % 7 {
                0 => (next() % 2001) as f64 - 1000.0,
                1 => f64::from_bits(next() % (1 << 52)) * if i % 2 == 0 { 1.0 } else { -1.0 },
                _ => (next() as f64 / u64::MAX as f64 - 0.5) * 1e3,
            })
            .collect();
        v.extend([
            0.0,
            -0.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN,
            f64::MAX,
        ]);
        let mut want = v.clone();
        want.sort_by(f64::total_cmp);
        radsort::sort(&mut v);
        let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&v), bits(&want));
    }
}
