//! Feature parameters, ISO 25178-2 §5: watershed segmentation into dales (and, on the inverted
//! heights, hills), Wolf pruning, and the statistics of the significant motifs: Spd, Spc, S5p,
//! S5v, S10z, Sda, Sha, Sdv, Shv (and Svd, Svc, their pit counterparts).
//!
//! Segmentation (the same rules as surfalize 0.19.2, the parity reference): every valid pixel
//! drains to its lowest 8-neighbour when that one is strictly lower (the first in scan order
//! on ties); pixels without a lower neighbour are sinks, 8-connected sinks seed one basin
//! (numbered in scan order); each basin is the set of pixels draining to its seed. Two
//! adjacent basins (8-neighbours) connect at their saddle, the lowest over their common
//! border of the higher of the two heights. Wolf pruning: the motif with the smallest local
//! depth (lowest bounding saddle minus its pit) below `pruning_pct` % of Sz is merged into the
//! neighbour across that saddle (the deeper pit survives), until every motif is at least that
//! deep. Default 5 % of Sz (ISO 25178-3).
//!
//! Significant motifs: the pruned motifs that touch neither the border of the map nor a gap
//! (NaN; a gap is an unknown boundary, so a motif beside it is incomplete like one at the
//! border). Attributes: the pit (dale) / peak (hill) height about the mean of the valid points,
//! the local mean curvature there -(d2z/dx2 + d2z/dy2) / 2 (central differences; pits or peaks
//! on the border or beside a gap skipped), the area (pixels x px py) and the volume: for a
//! dale the void below its lowest bounding saddle inside the motif, for a hill the material
//! above its saddle (the saddle of the inverted heights), sum |z - saddle| px py over the motif
//! pixels on the right side of the saddle.
//!
//! Spd, Svd: significant hills / dales per unit area, the area being (cols - 1) px (rows - 1)
//! py times the fraction of valid points (1/um^2). Spc, Svc: mean curvature at the peaks / pits
//! (1/um; Svc is negative). S5p: mean height of the five highest peaks, S5v: mean depth of the
//! five deepest pits (fewer when fewer exist), S10z = S5p + S5v (um). Sha, Sda: mean hill /
//! dale area (um^2); Shv, Sdv: mean hill / dale volume (um^3). No significant motif: NaN.

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;

use rayon::prelude::*;
use rustc_hash::FxHashMap;
use serde::Serialize;

use super::{Grid, MetrologyError};

/// ISO 25178-3 default Wolf pruning threshold, % of Sz.
pub const DEFAULT_PRUNING_PCT: f64 = 5.0;
const FIVE: usize = 5;

/// The feature parameters (see the module documentation for units).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FeatureParams {
    #[serde(rename = "Spd")]
    pub spd: f64,
    #[serde(rename = "Spc")]
    pub spc: f64,
    #[serde(rename = "S5p")]
    pub s5p: f64,
    #[serde(rename = "S5v")]
    pub s5v: f64,
    #[serde(rename = "S10z")]
    pub s10z: f64,
    #[serde(rename = "Sda")]
    pub sda: f64,
    #[serde(rename = "Sha")]
    pub sha: f64,
    #[serde(rename = "Sdv")]
    pub sdv: f64,
    #[serde(rename = "Shv")]
    pub shv: f64,
    #[serde(rename = "Svd")]
    pub svd: f64,
    #[serde(rename = "Svc")]
    pub svc: f64,
}

/// One significant motif: its pit (index into the map), area (px) and volume (um * px).
#[derive(Debug, Clone, Copy)]
pub struct Motif {
    pub critical_index: usize,
    pub area_px: usize,
    pub volume_um_px: f64,
}

const OFFSETS: [(isize, isize); 8] = [
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, -1),
    (0, 1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// Wolf pruning's queue of (depth, basin, version), smallest first in the order of
/// (depth by `f64::total_cmp`, basin, version): each entry one u128 whose integer order is
/// that order (cheaper to compare than the tuple), the entries queued at the start sorted once
/// and read in order, the entries pushed later in a binary heap, the smaller of the two heads
/// popped. The same pops, in the same order, as one heap of the tuples.
struct DepthQueue {
    sorted: Vec<u128>,
    head: usize,
    pushed: BinaryHeap<Reverse<u128>>,
}

impl DepthQueue {
    fn entry(depth: f64, basin: u32, version: u32) -> u128 {
        // total_cmp's key (flip the magnitude bits of negatives), then the sign bit flipped so
        // that unsigned order is its signed order.
        let b = depth.to_bits() as i64;
        let key = ((b ^ ((((b >> 63) as u64) >> 1) as i64)) as u64) ^ (1 << 63);
        ((key as u128) << 64) | ((basin as u128) << 32) | version as u128
    }

    fn of(mut initial: Vec<u128>) -> Self {
        initial.par_sort_unstable();
        Self {
            sorted: initial,
            head: 0,
            pushed: BinaryHeap::new(),
        }
    }

    fn push(&mut self, e: u128) {
        self.pushed.push(Reverse(e));
    }

    /// The smallest entry's (basin, version).
    fn pop(&mut self) -> Option<(u32, u32)> {
        let from_sorted = self.sorted.get(self.head).copied();
        let e = match (from_sorted, self.pushed.peek()) {
            (Some(a), Some(&Reverse(b))) if b < a => self.pushed.pop().map(|Reverse(b)| b),
            (Some(a), _) => {
                self.head += 1;
                Some(a)
            }
            (None, _) => self.pushed.pop().map(|Reverse(b)| b),
        }?;
        Some(((e >> 32) as u32, e as u32))
    }
}

/// Index of (r, c) in a `rows` x `cols` grid, `None` outside it.
fn cell(r: isize, c: isize, rows: usize, cols: usize) -> Option<usize> {
    if r < 0 || c < 0 || r >= rows as isize || c >= cols as isize {
        None
    } else {
        Some(r as usize * cols + c as usize)
    }
}

/// Height `i` of the map being segmented: `z` itself (dales) or `-z` (hills, NEG), negated on
/// the fly rather than copied (negation is exact: the same bits as an inverted copy).
#[inline(always)]
fn h<const NEG: bool>(z: &[f64], i: usize) -> f64 {
    if NEG {
        -z[i]
    } else {
        z[i]
    }
}

/// No pixel (a pit not yet found, a basin without neighbours' saddle).
const NO_PIXEL: u32 = u32::MAX;

/// The height of pixel `i` as [`h`] reads it; +infinity for [`NO_PIXEL`].
#[inline(always)]
fn height_at<const NEG: bool>(z: &[f64], i: u32) -> f64 {
    if i == NO_PIXEL {
        f64::INFINITY
    } else {
        h::<NEG>(z, i as usize)
    }
}

/// A neighbour list entry: the neighbouring basin and the pixel whose height is the saddle
/// between the two (see [`saddles`]).
type Neighbour = (u32, u32);

/// A pair of adjacent basins (a << 32 | b, a < b) and the pixel of its saddle; packed, 12
/// bytes (there are a few per basin).
#[derive(Clone, Copy)]
#[repr(C, packed(4))]
struct SaddlePair {
    key: u64,
    pixel: u32,
}

/// The one u32 per pixel of the segmentation, in turn its drain, its sink's union-find
/// parent and its label (labels and indices < 2^30, see [`MAX_POINTS`]).
const GAP: u32 = u32::MAX;
/// A sink; the low bits are its union-find parent (itself at first).
const SINK: u32 = 1 << 30;
/// Labelled; the low bits are the label.
const LAB: u32 = 1 << 31;
const LOW: u32 = SINK - 1;
/// The largest map the segmentation labels (pixel indices and labels in 30 bits).
pub const MAX_POINTS: usize = LOW as usize;

/// Step 1, steepest descent: each pixel's drain (`SINK | itself` for a sink; [`GAP`] for a gap).
fn drains<const NEG: bool>(z: &[f64], rows: usize, cols: usize) -> Vec<u32> {
    let at = |r: isize, c: isize| cell(r, c, rows, cols);
    let mut drain = vec![0u32; rows * cols];
    drain.par_chunks_mut(cols).enumerate().for_each(|(r, out)| {
        for (c, o) in out.iter_mut().enumerate() {
            let i = r * cols + c;
            let zi = h::<NEG>(z, i);
            if zi.is_nan() {
                *o = GAP;
                continue;
            }
            let (mut lo, mut li) = (f64::INFINITY, i);
            if r > 0 && c > 0 && r + 1 < rows && c + 1 < cols {
                // Interior: no bounds to check.
                let w = cols;
                for j in [
                    i - w - 1,
                    i - w,
                    i - w + 1,
                    i - 1,
                    i + 1,
                    i + w - 1,
                    i + w,
                    i + w + 1,
                ] {
                    let v = h::<NEG>(z, j);
                    if v < lo {
                        lo = v;
                        li = j;
                    }
                }
            } else {
                for (dy, dx) in OFFSETS {
                    if let Some(j) = at(r as isize + dy, c as isize + dx) {
                        let v = h::<NEG>(z, j);
                        if v < lo {
                            lo = v;
                            li = j;
                        }
                    }
                }
            }
            *o = if lo < zi { li as u32 } else { SINK | i as u32 };
        }
    });
    drain
}

/// The union-find root of sink `a` (path halving); stops early at a labelled sink, whose
/// index it returns.
fn sink_root(v: &mut [u32], mut a: usize) -> usize {
    loop {
        let e = v[a];
        if e & LAB != 0 {
            return a;
        }
        let p = (e & LOW) as usize;
        if p == a {
            return a;
        }
        let pe = v[p];
        if pe & LAB != 0 {
            return p;
        }
        v[a] = pe;
        a = (pe & LOW) as usize;
    }
}

/// Steps 2-3, in place on the drains: sinks, 8-connected, numbered by their first pixel in
/// scan order (1-based), and every pixel labelled with its sink's number (0: a gap). Returns
/// the labels and the number of basins.
fn label_basins(mut v: Vec<u32>, rows: usize, cols: usize) -> (Vec<u32>, usize) {
    let n = rows * cols;
    let at = |r: isize, c: isize| cell(r, c, rows, cols);
    let is_sink = |e: u32| e != GAP && e & SINK != 0;
    // 2. Union of adjacent sinks, the lower index the root: a component's root is its first
    // pixel in scan order.
    for i in 0..n {
        if !is_sink(v[i]) {
            continue;
        }
        let (r, c) = ((i / cols) as isize, (i % cols) as isize);
        for (dy, dx) in [(-1, -1), (-1, 0), (-1, 1), (0, -1)] {
            if let Some(j) = at(r + dy, c + dx) {
                if is_sink(v[j]) {
                    let (a, b) = (sink_root(&mut v, i), sink_root(&mut v, j));
                    if a != b {
                        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
                        v[hi] = SINK | lo as u32;
                    }
                }
            }
        }
    }
    // Roots numbered in scan order (a root precedes the rest of its component).
    let mut count = 0u32;
    for i in 0..n {
        if !is_sink(v[i]) {
            continue;
        }
        let root = sink_root(&mut v, i);
        if v[root] & LAB == 0 {
            count += 1;
            v[root] = LAB | count;
        }
        v[i] = v[root];
    }
    // 3. Every pixel takes its sink's label (paths strictly descend: follow and memoise).
    let mut path = Vec::new();
    for i in 0..n {
        if v[i] == GAP || v[i] & LAB != 0 {
            continue;
        }
        let mut j = i;
        while v[j] & LAB == 0 {
            path.push(j);
            j = v[j] as usize;
        }
        let l = v[j];
        for &p in &path {
            v[p] = l;
        }
        path.clear();
    }
    v.par_iter_mut()
        .for_each(|e| *e = if *e == GAP { 0 } else { *e & !LAB });
    (v, count as usize)
}

/// Per basin (index = label): its pit. Indices, not heights, are kept (the height is read
/// from the map when wanted: the same value, a third of the memory per basin).
struct Basins {
    /// The pit: its first index in scan order.
    crit: Vec<u32>,
    /// Pixels (< 2^30, see [`MAX_POINTS`]).
    area: Vec<u32>,
    /// On the map's border or beside a gap: not a whole motif.
    incomplete: Vec<bool>,
}

/// Step 4: per basin, the pit, the pixel count and whether it is incomplete. Bands of rows in
/// parallel (one per thread), merged in band order: the pit is still the first lowest pixel
/// in scan order, the counts are integers.
fn basin_stats<const NEG: bool>(
    z: &[f64],
    label: &[u32],
    rows: usize,
    cols: usize,
    m: usize,
) -> Basins {
    let any_gap = z.par_iter().any(|v| v.is_nan());
    let bands = rayon::current_num_threads().clamp(1, rows.max(1));
    let band_rows = rows.div_ceil(bands);
    let parts: Vec<Basins> = (0..bands)
        .into_par_iter()
        .map(|b| {
            let r1 = ((b + 1) * band_rows).min(rows);
            basin_stats_of_rows::<NEG>(z, label, (rows, cols), b * band_rows..r1, m, any_gap)
        })
        .collect();
    let mut parts = parts.into_iter();
    let Some(mut all) = parts.next() else {
        return basin_stats_of_rows::<NEG>(z, label, (rows, cols), 0..0, m, any_gap);
    };
    for part in parts {
        for l in 1..=m {
            if height_at::<NEG>(z, part.crit[l]) < height_at::<NEG>(z, all.crit[l]) {
                all.crit[l] = part.crit[l];
            }
            all.area[l] += part.area[l];
            all.incomplete[l] |= part.incomplete[l];
        }
    }
    all
}

/// [`basin_stats`] of the rows `band` alone.
fn basin_stats_of_rows<const NEG: bool>(
    z: &[f64],
    label: &[u32],
    (rows, cols): (usize, usize),
    band: std::ops::Range<usize>,
    m: usize,
    any_gap: bool,
) -> Basins {
    let at = |r: isize, c: isize| cell(r, c, rows, cols);
    let mut crit = vec![NO_PIXEL; m + 1];
    let mut area = vec![0u32; m + 1];
    let mut incomplete = vec![false; m + 1];
    for r in band {
        for c in 0..cols {
            let i = r * cols + c;
            let l = label[i] as usize;
            if l == 0 {
                continue;
            }
            area[l] += 1;
            if h::<NEG>(z, i) < height_at::<NEG>(z, crit[l]) {
                crit[l] = i as u32;
            }
            let on_border = r == 0 || c == 0 || r + 1 == rows || c + 1 == cols;
            let beside_gap = any_gap
                && OFFSETS
                    .iter()
                    .any(|&(dy, dx)| z[at(r as isize + dy, c as isize + dx).unwrap_or(i)].is_nan());
            if on_border || beside_gap {
                incomplete[l] = true;
            }
        }
    }
    Basins {
        crit,
        area,
        incomplete,
    }
}

/// Step 5, saddles between adjacent basins (8-neighbours): min over the border of the higher
/// height, one per pair of basins, sorted by the pair (see [`NeighbourLists::of_pairs`]).
/// Blocks of rows collect their pairs in a map (a border repeats one pair many times), so
/// only distinct pairs per block are sorted.
fn saddles<const NEG: bool>(z: &[f64], label: &[u32], rows: usize, cols: usize) -> Vec<SaddlePair> {
    let at = |r: isize, c: isize| cell(r, c, rows, cols);
    let height = |i: u32| h::<NEG>(z, i as usize);
    const ROWS_PER_BLOCK: usize = 32;
    let mut pairs: Vec<SaddlePair> = (0..rows.div_ceil(ROWS_PER_BLOCK))
        .into_par_iter()
        .flat_map_iter(|b| {
            let mut map: FxHashMap<u64, u32> = FxHashMap::default();
            for r in b * ROWS_PER_BLOCK..((b + 1) * ROWS_PER_BLOCK).min(rows) {
                for c in 0..cols {
                    let i = r * cols + c;
                    let la = label[i];
                    if la == 0 {
                        continue;
                    }
                    for (dy, dx) in [(0isize, 1isize), (1, 0), (1, 1), (1, -1)] {
                        if let Some(j) = at(r as isize + dy, c as isize + dx) {
                            let lb = label[j];
                            if lb != 0 && lb != la {
                                let (a, b) = if la < lb { (la, lb) } else { (lb, la) };
                                // The higher of the two (either on a tie: the same height).
                                let s = if height(j as u32) > height(i as u32) {
                                    j
                                } else {
                                    i
                                } as u32;
                                map.entry(((a as u64) << 32) | b as u64)
                                    .and_modify(|v| {
                                        if height(s) < height(*v) {
                                            *v = s
                                        }
                                    })
                                    .or_insert(s);
                            }
                        }
                    }
                }
            }
            map.into_iter()
                .map(|(key, pixel)| SaddlePair { key, pixel })
        })
        .collect();
    // A pair met in two blocks keeps its lower saddle.
    pairs.par_sort_unstable_by_key(|p| p.key);
    pairs.dedup_by(|later, kept| {
        let same = { later.key } == { kept.key };
        if same && height(later.pixel) < height(kept.pixel) {
            kept.pixel = later.pixel;
        }
        same
    });
    pairs
}

/// No segment after this one in its chain.
const END: u32 = u32::MAX;

/// The basins' neighbour lists of [`wolf_prune`] in one store: each basin's first list is a
/// segment of it, in basin order (compressed sparse rows); a merge links the merged basin's
/// segments behind the survivor's instead of copying them. Nothing grows while pruning (a
/// compacted list is written back into its own segments): with a `Vec` per basin, joined
/// lists reallocated and the pruning grew its lists by about three quarters (of a
/// 4096^2 roughness map's 37 MB), besides a header and an allocation per basin.
struct NeighbourLists {
    entries: Vec<Neighbour>,
    /// Segment `s` may hold `entries[start[s]..start[s + 1]]`.
    start: Vec<usize>,
    /// The entries in use in segment `s`, from its start.
    used: Vec<u32>,
    /// The next segment of the chain, [`END`] after the last.
    next: Vec<u32>,
    /// Per basin, the last segment of its chain (the first is the basin's own).
    last: Vec<u32>,
    /// Per basin, the entries in its chain (< 2^32: a chain is compacted before it holds
    /// more than twice its distinct neighbours and a few, and basins are < 2^30).
    len: Vec<u32>,
}

impl NeighbourLists {
    /// The lists of the distinct `pairs` (sorted by key): one entry per pair in each of its
    /// two basins' lists, in ascending neighbour.
    fn of_pairs(pairs: &[SaddlePair], m: usize) -> Self {
        let split = |k: u64| ((k >> 32) as usize, (k & 0xffff_ffff) as usize);
        let mut used = vec![0u32; m + 1];
        for p in pairs {
            let (a, b) = split(p.key);
            used[a] += 1;
            used[b] += 1;
        }
        let mut start = Vec::with_capacity(m + 2);
        let mut at = 0usize;
        start.push(at);
        for &d in &used {
            at += d as usize;
            start.push(at);
        }
        let mut entries = vec![(0u32, 0u32); at];
        used.fill(0);
        for p in pairs {
            let (a, b) = split(p.key);
            entries[start[a] + used[a] as usize] = (b as u32, p.pixel);
            used[a] += 1;
            entries[start[b] + used[b] as usize] = (a as u32, p.pixel);
            used[b] += 1;
        }
        NeighbourLists {
            entries,
            start,
            len: used.clone(),
            used,
            next: vec![END; m + 1],
            last: (0..=m as u32).collect(),
        }
    }

    fn len(&self, basin: u32) -> usize {
        self.len[basin as usize] as usize
    }

    /// The entries of `basin`'s list, segment by segment.
    fn entries(&self, basin: u32) -> impl Iterator<Item = Neighbour> + '_ {
        let mut s = basin;
        std::iter::from_fn(move || {
            (s != END).then(|| {
                let su = s as usize;
                s = self.next[su];
                &self.entries[self.start[su]..][..self.used[su] as usize]
            })
        })
        .flatten()
        .copied()
    }

    /// `basin`'s list becomes `list`, which is no longer than it (a compacted copy): written
    /// into its segments in order, the chain cut after the last one used.
    fn replace(&mut self, basin: u32, list: &[Neighbour]) {
        let mut rest = list;
        let mut s = basin;
        loop {
            let su = s as usize;
            let n = (self.start[su + 1] - self.start[su]).min(rest.len());
            self.entries[self.start[su]..][..n].copy_from_slice(&rest[..n]);
            self.used[su] = n as u32;
            rest = &rest[n..];
            if rest.is_empty() || self.next[su] == END {
                self.next[su] = END;
                self.last[basin as usize] = s;
                break;
            }
            s = self.next[su];
        }
        debug_assert!(
            rest.is_empty(),
            "a replacement list is longer than the list"
        );
        self.len[basin as usize] = list.len() as u32;
    }

    /// `merged`'s list joins the end of `survivor`'s (and is no longer its own).
    fn join(&mut self, survivor: u32, merged: u32) {
        let (su, mu) = (survivor as usize, merged as usize);
        if self.len[mu] == 0 {
            return;
        }
        self.next[self.last[su] as usize] = merged;
        self.last[su] = self.last[mu];
        self.len[su] += self.len[mu];
        self.len[mu] = 0;
    }
}

/// What Wolf pruning leaves: per basin whether it survives, where it merged, its lowest
/// saddle; `crit` is updated to the merged basins' pits.
struct Pruned {
    min_saddle: Vec<f64>,
    alive: Vec<bool>,
    merged_into: Vec<u32>,
}

/// The basin `x` has merged into (path halving; `merged_into` keeps every basin's root).
fn merged_root(merged_into: &mut [u32], mut x: u32) -> u32 {
    while merged_into[x as usize] != x {
        let p = merged_into[merged_into[x as usize] as usize];
        merged_into[x as usize] = p;
        x = p;
    }
    x
}

/// Step 6, Wolf pruning: the basin of the smallest depth (lowest saddle - pit) below
/// `threshold` merges into its neighbour over that saddle, until none is left.
///
/// The neighbour lists are lazy: a merge appends the merged basin's list to the survivor's
/// and leaves the other basins' entries pointing at it; an entry means its neighbour's root
/// ([`merged_root`]), the saddle between two basins is the lowest of their entries for each
/// other, and an entry to the basin itself is internal. That is the map of neighbour ->
/// saddle a merge would otherwise rewrite in every neighbour (min of the two saddles), read
/// when needed: a list is compacted (roots, one entry per neighbour at its lowest saddle)
/// when it is rescanned or has doubled. The lowest saddle and its neighbour per basin are
/// kept as before (ties: lowest label).
fn wolf_prune<const NEG: bool>(
    z: &[f64],
    mut lists: NeighbourLists,
    crit: &mut [u32],
    threshold: f64,
    m: usize,
) -> Pruned {
    let height = |i: u32| h::<NEG>(z, i as usize);
    let pit = |i: u32| height_at::<NEG>(z, i);
    let mut min_saddle = vec![f64::INFINITY; m + 1];
    let mut min_nb = vec![0u32; m + 1];
    let lowest = |list: &mut dyn Iterator<Item = Neighbour>| {
        let mut best = (f64::INFINITY, 0u32);
        for (nb, pixel) in list {
            let s = height(pixel);
            // Lowest saddle, then lowest label: independent of the list's order.
            if s < best.0 || (s == best.0 && nb < best.1) {
                best = (s, nb);
            }
        }
        best
    };
    // Every list starts compact (one entry per neighbour).
    for r in 1..=m {
        let (s, nb) = lowest(&mut lists.entries(r as u32));
        min_saddle[r] = s;
        min_nb[r] = nb;
    }
    let mut clean_len: Vec<u32> = (0..=m as u32).map(|r| lists.len(r) as u32).collect();
    let mut merged_into: Vec<u32> = (0..=m as u32).collect();
    // Roots, without `x` itself, one entry per root at its lowest saddle.
    let compacted = |list: &mut Vec<Neighbour>, x: u32, merged_into: &mut [u32]| {
        for e in list.iter_mut() {
            e.0 = merged_root(merged_into, e.0);
        }
        list.retain(|e| e.0 != x);
        list.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(height(a.1).total_cmp(&height(b.1))));
        list.dedup_by_key(|e| e.0);
    };
    // A compacted copy of `x`'s list in `scratch`.
    let copy_compacted =
        |lists: &NeighbourLists, x: u32, merged_into: &mut [u32], scratch: &mut Vec<Neighbour>| {
            scratch.clear();
            scratch.extend(lists.entries(x));
            compacted(scratch, x, merged_into);
        };
    // `x`'s list compacted, left in `scratch` too.
    let compact = |lists: &mut NeighbourLists,
                   x: u32,
                   merged_into: &mut [u32],
                   scratch: &mut Vec<Neighbour>| {
        copy_compacted(lists, x, merged_into, scratch);
        lists.replace(x, scratch);
    };
    let mut version = vec![0u32; m + 1];
    let mut alive = vec![true; m + 1];
    // Only depths below the threshold are queued: the loop would stop at the first other.
    // (As the loop's `h >= threshold` test: a NaN depth or threshold queues.)
    let queued = |h: f64| {
        !matches!(
            h.partial_cmp(&threshold),
            Some(Ordering::Greater | Ordering::Equal)
        )
    };
    let mut queue = DepthQueue::of(
        (1..=m)
            .map(|r| (min_saddle[r] - pit(crit[r]), r))
            .filter(|&(h, _)| queued(h))
            .map(|(h, r)| DepthQueue::entry(h, r as u32, 0))
            .collect(),
    );
    let mut moved_list: Vec<Neighbour> = Vec::new();
    let mut compact_list: Vec<Neighbour> = Vec::new();
    while let Some((r, ver)) = queue.pop() {
        let ru = r as usize;
        if !alive[ru] || ver != version[ru] {
            continue;
        }
        let nb = min_nb[ru];
        let nbu = nb as usize;
        // r's neighbours but nb (and r), at their lowest saddle to r.
        copy_compacted(&lists, r, &mut merged_into, &mut moved_list);
        moved_list.retain(|e| e.0 != nb);
        let mut moved = (f64::INFINITY, 0u32);
        for &(other, pixel) in &moved_list {
            let s = height(pixel);
            if min_nb[other as usize] == r {
                min_nb[other as usize] = nb;
            }
            // The saddle nb - other becomes min(nb's, s): below nb's lowest only when s is.
            if s < moved.0 || (s == moved.0 && other < moved.1) {
                moved = (s, other);
            }
        }
        lists.replace(r, &moved_list);
        lists.join(nb, r);
        if pit(crit[ru]) < pit(crit[nbu]) {
            crit[nbu] = crit[ru];
        }
        alive[ru] = false;
        merged_into[ru] = nb;
        if min_nb[nbu] == r {
            compact(&mut lists, nb, &mut merged_into, &mut compact_list);
            clean_len[nbu] = lists.len(nb) as u32;
            let (s, b) = lowest(&mut compact_list.iter().copied());
            min_saddle[nbu] = s;
            min_nb[nbu] = b;
        } else {
            if moved.0 < min_saddle[nbu] {
                min_saddle[nbu] = moved.0;
                min_nb[nbu] = moved.1;
            }
            if lists.len(nb) > 2 * clean_len[nbu] as usize + 8 {
                compact(&mut lists, nb, &mut merged_into, &mut compact_list);
                clean_len[nbu] = lists.len(nb) as u32;
            }
        }
        version[nbu] += 1;
        let h = min_saddle[nbu] - pit(crit[nbu]);
        if queued(h) {
            queue.push(DepthQueue::entry(h, nb, version[nbu]));
        }
    }
    drop(queue);
    Pruned {
        min_saddle,
        alive,
        merged_into,
    }
}

/// Watershed + Wolf pruning of the dales of `d` (NaN = gap); the significant motifs.
/// `sz` is the range of the valid heights (the pruning reference).
///
/// # Panics
/// On more than [`MAX_POINTS`] points ([`feature_params`] returns an error instead).
pub fn segment_dales(d: &[f64], rows: usize, cols: usize, pruning_pct: f64, sz: f64) -> Vec<Motif> {
    segment::<false>(d, rows, cols, pruning_pct, sz)
}

/// [`segment_dales`] of `z` (NEG false) or of `-z` (NEG true: the hills).
fn segment<const NEG: bool>(
    z: &[f64],
    rows: usize,
    cols: usize,
    pruning_pct: f64,
    sz: f64,
) -> Vec<Motif> {
    assert!(
        rows * cols <= MAX_POINTS,
        "segmentation of {rows} x {cols} points: at most {MAX_POINTS} (feature_params checks)"
    );
    let (label, m) = label_basins(drains::<NEG>(z, rows, cols), rows, cols);
    let Basins {
        mut crit,
        area,
        incomplete,
    } = basin_stats::<NEG>(z, &label, rows, cols, m);
    let pairs = saddles::<NEG>(z, &label, rows, cols);
    // The pruning does not read the labels (half the map's size): they are made again for
    // the volumes, the same labels (the same steps on the same heights), so that the labels,
    // the neighbour lists and the pruning's queue are never held at once (on a 4096^2
    // roughness map the segmentation's peak was the three together, 2.1 x the map).
    drop(label);
    let lists = NeighbourLists::of_pairs(&pairs, m);
    drop(pairs);
    let Pruned {
        min_saddle,
        alive,
        merged_into,
    } = wolf_prune::<NEG>(z, lists, &mut crit, pruning_pct / 100.0 * sz, m);
    let (label, _) = label_basins(drains::<NEG>(z, rows, cols), rows, cols);
    // 7. Roots, their areas and incompleteness.
    let mut root = vec![0u32; m + 1];
    for (r, out) in root.iter_mut().enumerate().skip(1) {
        let mut x = r as u32;
        while merged_into[x as usize] != x {
            x = merged_into[x as usize];
        }
        *out = x;
    }
    let mut root_area = vec![0u32; m + 1];
    let mut root_incomplete = vec![false; m + 1];
    for r in 1..=m {
        let x = root[r] as usize;
        root_area[x] += area[r];
        root_incomplete[x] |= incomplete[r];
    }
    let significant = |x: usize| alive[x] && !root_incomplete[x] && min_saddle[x].is_finite();
    // 8. Volumes below each significant root's saddle.
    let mut volume = vec![0.0f64; m + 1];
    for (i, &l) in label.iter().enumerate() {
        if l == 0 {
            continue;
        }
        let x = root[l as usize] as usize;
        if significant(x) {
            let depth = min_saddle[x] - h::<NEG>(z, i);
            if depth > 0.0 {
                volume[x] += depth;
            }
        }
    }
    (1..=m)
        .filter(|&x| significant(x))
        .map(|x| Motif {
            critical_index: crit[x] as usize,
            area_px: root_area[x] as usize,
            volume_um_px: volume[x],
        })
        .collect()
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (mut s, mut k) = (0.0, 0usize);
    for x in v {
        s += x;
        k += 1;
    }
    if k == 0 {
        f64::NAN
    } else {
        s / k as f64
    }
}

/// Mean of the `FIVE` largest values (fewer when fewer).
fn top_five_mean(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| b.total_cmp(a));
    v.truncate(FIVE);
    mean(v.into_iter())
}

/// The feature parameters of `g` with Wolf pruning at `pruning_pct` % of Sz.
pub fn feature_params(g: &Grid, pruning_pct: f64) -> Result<FeatureParams, MetrologyError> {
    let z = g.heights_um;
    let (rows, cols) = (g.rows(), g.cols());
    let super::HeightSummary {
        valid,
        lo,
        hi,
        mean: mean_z,
    } = super::height_summary(g)?;
    let sz = hi - lo;
    if z.len() > MAX_POINTS {
        return Err(MetrologyError::TooManyPoints {
            points: z.len(),
            max: MAX_POINTS,
        });
    }
    // One after the other, not side by side: each holds a label per pixel (half the map) and
    // its basins' neighbour lists; together they were 2.5 x the map (parallel inside each).
    let hills = segment::<true>(z, rows, cols, pruning_pct, sz);
    let dales = segment::<false>(z, rows, cols, pruning_pct, sz);
    let (px, py) = (g.pitch_x_um(), g.pitch_y_um());
    let curvature = |i: usize| -> Option<f64> {
        let (r, c) = (i / cols, i % cols);
        if r == 0 || c == 0 || r + 1 >= rows || c + 1 >= cols {
            return None;
        }
        let (l, rr, u, dn) = (z[i - 1], z[i + 1], z[i - cols], z[i + cols]);
        let d2x = (rr - 2.0 * z[i] + l) / (px * px);
        let d2y = (dn - 2.0 * z[i] + u) / (py * py);
        let k = -0.5 * (d2x + d2y);
        (!k.is_nan()).then_some(k)
    };
    let area = (cols.saturating_sub(1) as f64 * px)
        * (rows.saturating_sub(1) as f64 * py)
        * (valid as f64 / z.len() as f64);
    let cell = px * py;
    let s5p = top_five_mean(hills.iter().map(|m| z[m.critical_index] - mean_z).collect());
    let s5v = top_five_mean(dales.iter().map(|m| mean_z - z[m.critical_index]).collect());
    Ok(FeatureParams {
        spd: hills.len() as f64 / area,
        spc: mean(hills.iter().filter_map(|m| curvature(m.critical_index))),
        s5p,
        s5v,
        s10z: s5p + s5v,
        sda: mean(dales.iter().map(|m| m.area_px as f64 * cell)),
        sha: mean(hills.iter().map(|m| m.area_px as f64 * cell)),
        sdv: mean(dales.iter().map(|m| m.volume_um_px * cell)),
        shv: mean(hills.iter().map(|m| m.volume_um_px * cell)),
        svd: dales.len() as f64 / area,
        svc: mean(dales.iter().filter_map(|m| curvature(m.critical_index))),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Copy, PartialEq)]
    struct Key(f64);
    impl Eq for Key {}
    impl PartialOrd for Key {
        fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
            Some(self.cmp(o))
        }
    }
    impl Ord for Key {
        fn cmp(&self, o: &Self) -> Ordering {
            self.0.total_cmp(&o.0)
        }
    }

    /// The packed queue pops what one heap of (total_cmp depth, basin, version) tuples pops,
    /// in the same order, pushes interleaved with pops: negative, -0 and +0, equal depths,
    /// infinities and NaN included.
    #[test]
    fn depth_queue_pops_as_the_tuple_heap() {
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let special = [
            0.0,
            -0.0,
            -1.5,
            1.5,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            1e-300,
        ];
        let depth = |n: u64| {
            if n.is_multiple_of(5) {
                special[(n / 5 % special.len() as u64) as usize]
            } else {
                ((n >> 20) % 1000) as f64 / 8.0 - 40.0
            }
        };
        let initial: Vec<(f64, u32)> = (0..2000u32).map(|b| (depth(next()), b % 700)).collect();
        let mut heap: BinaryHeap<Reverse<(Key, u32, u32)>> = initial
            .iter()
            .map(|&(d, b)| Reverse((Key(d), b, 0)))
            .collect();
        let mut queue = DepthQueue::of(
            initial
                .iter()
                .map(|&(d, b)| DepthQueue::entry(d, b, 0))
                .collect(),
        );
        let mut popped = 0;
        loop {
            let want = heap.pop().map(|Reverse((_, b, v))| (b, v));
            let got = queue.pop();
            assert_eq!(got, want, "pop {popped}");
            if want.is_none() {
                break;
            }
            popped += 1;
            let n = next();
            if n % 3 != 0 && popped < 3000 {
                let (d, b, v) = (
                    depth(next()),
                    (n >> 8) as u32 % 700,
                    1 + (n >> 40) as u32 % 9,
                );
                heap.push(Reverse((Key(d), b, v)));
                queue.push(DepthQueue::entry(d, b, v));
            }
        }
        assert!(popped > 3000);
    }

    /// The one-store lists hold what a `Vec` per basin holds through merges: made from the
    /// pairs (both directions, ascending), a merged basin's list (compacted to a shorter one
    /// first, or emptied) joined behind the survivor's, the survivor's own list replaced by
    /// shorter ones, over random graphs and merge orders.
    #[test]
    fn neighbour_lists_hold_what_a_list_per_basin_holds() {
        let mut state = 0x2545_F491_4F6C_DD1D_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..200 {
            let m = 1 + (next() % 40) as usize;
            let mut keys: Vec<u64> = (0..next() % 120)
                .filter_map(|_| {
                    let a = 1 + next() % m as u64;
                    let b = 1 + next() % m as u64;
                    (a != b).then(|| (a.min(b) << 32) | a.max(b))
                })
                .collect();
            keys.sort_unstable();
            keys.dedup();
            let pairs: Vec<SaddlePair> = keys
                .iter()
                .map(|&key| SaddlePair {
                    key,
                    pixel: (next() % 1000) as u32,
                })
                .collect();
            let mut model: Vec<Vec<Neighbour>> = vec![Vec::new(); m + 1];
            for p in &pairs {
                let (a, b) = ((p.key >> 32) as usize, (p.key & 0xffff_ffff) as usize);
                model[a].push((b as u32, p.pixel));
                model[b].push((a as u32, p.pixel));
            }
            for l in &mut model {
                l.sort_unstable();
            }
            let mut lists = NeighbourLists::of_pairs(&pairs, m);
            // A merged basin's segments are the survivor's: only its length is its own (0).
            let same = |lists: &NeighbourLists, model: &[Vec<Neighbour>], alive: &[u32]| {
                (0..=m as u32).all(|b| {
                    let got: Vec<Neighbour> = lists.entries(b).collect();
                    let whole = got == model[b as usize] && lists.len(b) == got.len();
                    whole || (!alive.contains(&b) && lists.len(b) == 0)
                })
            };
            let mut alive: Vec<u32> = (0..=m as u32).collect();
            assert!(same(&lists, &model, &alive));
            alive.remove(0);
            while alive.len() > 1 {
                let r = alive.swap_remove((next() % alive.len() as u64) as usize);
                let nb = alive[(next() % alive.len() as u64) as usize];
                // A shorter list for the merged basin (a compaction), then the join.
                let mut shorter = std::mem::take(&mut model[r as usize]);
                shorter.truncate((next() % (shorter.len() as u64 + 1)) as usize);
                lists.replace(r, &shorter);
                lists.join(nb, r);
                model[nb as usize].extend_from_slice(&shorter);
                // Sometimes the survivor's own list replaced by a shorter one.
                if next() % 3 == 0 {
                    let keep = (next() % (model[nb as usize].len() as u64 + 1)) as usize;
                    let mut l = model[nb as usize][..keep].to_vec();
                    l.reverse();
                    lists.replace(nb, &l);
                    model[nb as usize] = l;
                }
                assert!(same(&lists, &model, &alive));
            }
        }
    }
}
